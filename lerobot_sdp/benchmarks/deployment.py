"""Deployment on the simulated robot: lerobot-rollout (sync, RTC) and async inference, per policy.

    lerobot-sdp-bench deployment --policy sdp_h2=PATH/pretrained_model --policy dp=PATH/pretrained_model \\
        --duration 60 --output_dir outputs/benchmarks/deployment

Each policy drives `pusht_sim` (Push-T at 10 Hz, first episode seeded) for `--duration` seconds under
each engine of `--engines`, through the real CLIs: `lerobot-rollout` for `sync` and `rtc`
(`--inference.queue_threshold=--rtc_threshold`), and for `async` the plugin's
`lerobot-sdp-policy-server` with LeRobot's `robot_client` (stopped by SIGINT, as Ctrl-C does, once
`--duration` seconds have passed since its control loop started). The robot records the actions it
received, the control ticks that passed without one (missed ticks), how far the commanded target
jumped between consecutive actions, and each episode's max reward.

A policy LeRobot cannot run under an engine (RTC needs `supports_rtc()`) gets a row that says so; a
run that fails gets its error and the path of its log. Output: OUTPUT_DIR/results.json and
results.md; every run's console in OUTPUT_DIR/logs/. Run it as the only heavy process on the machine:
inference time is what it measures. Checkpoints with a keypoint (environment-state) input need SDP's
`sdp_split_state` preprocessor step (`python -m lerobot_sdp.robots.prepare_policy DIR` adds it).
"""

import argparse
import json
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

from lerobot.configs.policies import PreTrainedConfig

from ..lerobot_cli import lerobot_bin, let_sigint_reach_children, subprocess_env
from ..processor_sdp import lacks_split_state_step

ENGINES = ("sync", "rtc", "async")
FPS = 10
CLIENT_READY = "Control loop thread starting"  # LeRobot's robot_client log line


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--policy",
        action="append",
        required=True,
        metavar="NAME=PATH",
        help="a pretrained_model folder, named for the table (repeat for each policy)",
    )
    p.add_argument("--engines", nargs="+", default=list(ENGINES), choices=ENGINES)
    p.add_argument("--duration", type=int, default=60, help="seconds per run")
    p.add_argument("--rtc_threshold", type=int, default=5, help="--inference.queue_threshold for rtc")
    p.add_argument("--port", type=int, default=8080, help="the async policy server's port (loopback)")
    p.add_argument("--output_dir", type=Path, default=Path("outputs/benchmarks/deployment"))


def parse_policies(specs: list[str]) -> dict[str, Path]:
    policies = {}
    for spec in specs:
        name, sep, path = spec.partition("=")
        if not sep or not name or not path:
            raise SystemExit(f"--policy takes NAME=PATH (a pretrained_model folder), got {spec!r}.")
        if not (Path(path) / "config.json").exists():
            raise SystemExit(f"--policy {name}: {path} has no config.json; pass a pretrained_model folder.")
        policies[name] = Path(path)
    return policies


def robot_ready_problem(path: Path) -> str | None:
    """Why the robot's joined `observation.state` cannot reach this policy, or None."""
    if not lacks_split_state_step(path, PreTrainedConfig.from_pretrained(path)):
        return None
    return (
        f"{path} takes the keypoints as a separate environment state, and its preprocessor lacks SDP's "
        f"`sdp_split_state` step: run `python -m lerobot_sdp.robots.prepare_policy {path}` first."
    )


def rollout_cmd(
    path: Path, stats: Path, calibration: Path, duration: int, rtc_threshold: int | None
) -> list[str]:
    cmd = [
        lerobot_bin("lerobot-rollout"),
        "--robot.type=pusht_sim",
        f"--robot.stats_path={stats}",
        f"--robot.calibration_dir={calibration}",
        "--robot.seed=0",
        f"--policy.path={path}",
        f"--fps={FPS}",
        f"--duration={duration}",
        "--device=cpu",
        "--return_to_initial_position=false",
    ]
    if rtc_threshold is not None:
        cmd += ["--inference.type=rtc", f"--inference.queue_threshold={rtc_threshold}"]
    return cmd


def client_cmd(path: Path, config: PreTrainedConfig, stats: Path, calibration: Path, port: int) -> list[str]:
    return [
        sys.executable,
        "-m",
        "lerobot.async_inference.robot_client",
        "--robot.type=pusht_sim",
        f"--robot.stats_path={stats}",
        f"--robot.calibration_dir={calibration}",
        "--robot.seed=0",
        f"--server_address=127.0.0.1:{port}",
        f"--policy_type={config.type}",
        f"--pretrained_name_or_path={path}",
        f"--actions_per_chunk={2 * config.n_action_steps}",
        f"--fps={FPS}",
    ]


class Logged:
    """A subprocess whose console goes to a log file, watched for a line."""

    def __init__(self, cmd: list[str], log: Path, watch: str | None = None):
        self.seen = threading.Event()
        self.file = log.open("w")
        self.proc = subprocess.Popen(
            cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=subprocess_env()
        )
        self.thread = threading.Thread(target=self._pump, args=(watch,), daemon=True)
        self.thread.start()

    def _pump(self, watch: str | None) -> None:
        for line in self.proc.stdout:
            self.file.write(line)
            if watch and watch in line:
                self.seen.set()

    def stop(self, sig: int = signal.SIGINT, timeout: float = 60) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
        try:
            rc = self.proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            rc = self.proc.wait()
        self.thread.join(timeout=10)
        self.file.close()
        return rc


def wait_for_port(port: int, proc: subprocess.Popen, timeout: float = 120) -> None:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if proc.poll() is not None:
            raise RuntimeError(f"the policy server exited (code {proc.returncode}) before listening")
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.5)
    raise RuntimeError(f"the policy server did not listen on port {port} within {timeout:.0f} s")


def run_async(
    path: Path, config: PreTrainedConfig, stats: Path, calibration: Path, log_dir: Path, name: str, args
) -> None:
    server_cmd = [
        lerobot_bin("lerobot-sdp-policy-server"),
        "--host=127.0.0.1",
        f"--port={args.port}",
        f"--fps={FPS}",
    ]
    server = Logged(server_cmd, log_dir / f"{name}_async_server.log")
    try:
        wait_for_port(args.port, server.proc)
        client = Logged(
            client_cmd(path, config, stats, calibration, args.port),
            log_dir / f"{name}_async.log",
            CLIENT_READY,
        )
        try:
            if not client.seen.wait(timeout=180):
                raise RuntimeError("the robot client did not start its control loop within 180 s")
            time.sleep(args.duration)
        finally:
            client.stop()
    finally:
        server.stop(signal.SIGTERM)


def summarise(stats: dict) -> dict:
    episodes = [*stats["episodes"], stats["current_episode"]]
    return {
        "actions_sent": stats["actions_sent"],
        "missed_ticks": stats["missed_ticks"],
        "action_jump_px": stats["action_jump_px"],
        "episode_max_rewards": [round(e["max_reward"], 3) for e in episodes if e["steps"]],
        "episode_steps": [e["steps"] for e in episodes if e["steps"]],
        "successes": sum(bool(e["success"]) for e in episodes),
    }


def measure(name: str, path: Path, engine: str, args) -> dict:
    row = {"policy": name, "path": str(path), "engine": engine, "duration_s": args.duration}
    config = PreTrainedConfig.from_pretrained(path)
    if engine == "rtc" and config.type != "sdp":
        return row | {
            "error": f"not run: LeRobot's `{config.type}` policy has no RTC support (supports_rtc())"
        }
    log_dir = args.output_dir / "logs"
    log_dir.mkdir(parents=True, exist_ok=True)
    stats_path = args.output_dir / "stats" / f"{name}_{engine}.json"
    stats_path.unlink(missing_ok=True)
    calibration = args.output_dir / "calibration"
    log = log_dir / f"{name}_{engine}.log"
    started = time.monotonic()
    try:
        if engine == "async":
            run_async(path, config, stats_path, calibration, log_dir, name, args)
        else:
            threshold = args.rtc_threshold if engine == "rtc" else None
            rollout = Logged(rollout_cmd(path, stats_path, calibration, args.duration, threshold), log)
            try:
                rollout.proc.wait(timeout=args.duration + 600)  # model loading and shutdown included
            except subprocess.TimeoutExpired:
                raise RuntimeError(
                    f"lerobot-rollout still ran {args.duration + 600} s after its start"
                ) from None
            finally:
                rc = rollout.stop()
            if rc != 0:
                raise RuntimeError(f"lerobot-rollout exited with code {rc}")
    except RuntimeError as e:
        return row | {"error": f"{e}; see {log}"}
    row["wall_s"] = round(time.monotonic() - started, 1)
    if not stats_path.exists():
        return row | {"error": f"the robot wrote no stats; see {log}"}
    row |= summarise(json.loads(stats_path.read_text()))
    if not row["actions_sent"]:  # e.g. the policy fails on every observation: the reason is in the logs
        row["error"] = (
            f"the robot received no action in {args.duration} s; see {log_dir / f'{name}_{engine}'}*.log"
        )
    return row


def markdown(rows: list[dict]) -> str:
    out = [
        "| policy | engine | actions sent | missed control ticks | target jump p50 / p95 / max (px) | "
        "max reward per episode (steps) |",
        "|" + "---|" * 6,
    ]
    for r in rows:
        if "error" in r:
            out.append(f"| {r['policy']} | {r['engine']} | {r['error']} | | | |")
            continue
        j = r["action_jump_px"] or {"p50": 0.0, "p95": 0.0, "max": 0.0}
        episodes = ", ".join(
            f"{m:.3f} ({s})" for m, s in zip(r["episode_max_rewards"], r["episode_steps"], strict=True)
        )
        out.append(
            f"| {r['policy']} | {r['engine']} | {r['actions_sent']} | {r['missed_ticks']} | "
            f"{j['p50']:.1f} / {j['p95']:.1f} / {j['max']:.1f} | {episodes} |"
        )
    return "\n".join(out) + "\n"


def run(args: argparse.Namespace) -> list[dict]:
    policies = parse_policies(args.policy)
    problems = [p for p in map(robot_ready_problem, policies.values()) if p]
    if problems:
        raise SystemExit("\n".join(problems))
    args.output_dir.mkdir(parents=True, exist_ok=True)
    let_sigint_reach_children()  # the clients are stopped with SIGINT
    rows = []
    for name, path in policies.items():
        for engine in args.engines:
            print(f"[deployment] {name} / {engine}: {args.duration} s on pusht_sim", flush=True)
            rows.append(measure(name, path, engine, args))
            (args.output_dir / "results.json").write_text(json.dumps({"fps": FPS, "rows": rows}, indent=2))
    table = markdown(rows)
    (args.output_dir / "results.md").write_text(table)
    print(table)
    return rows
