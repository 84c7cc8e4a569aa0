"""Deployment on the simulated robot in real time: lerobot-rollout (sync, RTC) and async inference.

    lerobot-sdp-bench deployment --policy sdp=PATH/pretrained_model --policy dp=PATH/pretrained_model \\
        --episodes 20 --output_dir outputs/benchmarks/deployment

Each policy drives `pusht_sim` (Push-T at 10 Hz in real time: the env steps every 0.1 s of the wall
clock, a tick without an action holds the last target) under each engine of `--engines`, through
the real CLIs: `lerobot-rollout` for `sync` and `rtc` (`--inference.queue_threshold=--rtc_threshold`),
and for `async` the plugin's `lerobot-sdp-policy-server` with LeRobot's `robot_client`. One episode
per run (`pusht_sim` runs one episode per connection, so every episode starts with a fresh policy),
episode i seeded `--seed` + i, the same seeds for every row; a run is stopped with SIGINT, as Ctrl-C
does, once its episode is over. `--parallel K` runs K episodes at once (K robots, each with its own
`lerobot-rollout` or `robot_client`; for async, one server serving all K), started together and
awaited together: more episodes in the same wall time, at the price of K control loops sharing the
CPU, which the missed-tick column shows. Per row: avg_max_reward and success with standard errors, missed
control ticks per episode, how far the commanded target jumped between consecutive actions.

A policy LeRobot cannot run under an engine (RTC needs `supports_rtc()`) gets a row that says so; a
run that fails gets its error and the path of its log. Output: OUTPUT_DIR/results.json (written
after every episode) and results.md; every run's console in OUTPUT_DIR/logs/. Run it as the only
heavy process on the machine: inference time is what it measures. Checkpoints with a keypoint
(environment-state) input need SDP's `sdp_split_state` preprocessor step
(`python -m lerobot_sdp.robots.prepare_policy DIR` adds it).
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
from ..pusht.evaluation import EVAL_SEED
from .episodes import figures
from .policy_args import add_policy_argument, parse_policies
from .report import table, with_se, write_json

ENGINES = ("sync", "rtc", "async")
FPS = 10
CLIENT_READY = "Control loop thread starting"  # LeRobot's robot_client log line


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_policy_argument(p)
    p.add_argument("--engines", nargs="+", default=list(ENGINES), choices=ENGINES)
    p.add_argument("--episodes", type=int, default=20, help="episodes per policy and engine")
    p.add_argument(
        "--parallel", type=int, default=1, help="episodes run at once, each on its own robot and process"
    )
    p.add_argument("--seed", type=int, default=EVAL_SEED, help="episode i starts from seed + i")
    p.add_argument("--episode_length", type=int, default=300, help="ticks per episode (Push-T: 300)")
    p.add_argument(
        "--rtc_threshold",
        type=int,
        default=0,
        help="--inference.queue_threshold for rtc: the inference time in ticks, rounded up, less one "
        "(0 for a chunk faster than a tick); below max_delay",
    )
    p.add_argument("--port", type=int, default=8080, help="the async policy server's port (loopback)")
    p.add_argument("--output_dir", type=Path, default=Path("outputs/benchmarks/deployment"))


def robot_ready_problem(path: Path) -> str | None:
    """Why the robot's joined `observation.state` cannot reach this policy, or None."""
    if not lacks_split_state_step(path, PreTrainedConfig.from_pretrained(path)):
        return None
    return (
        f"{path} takes the keypoints as a separate environment state, and its preprocessor lacks SDP's "
        f"`sdp_split_state` step: run `python -m lerobot_sdp.robots.prepare_policy {path}` first."
    )


def robot_args(stats: Path, calibration: Path, seed: int, episode_length: int) -> list[str]:
    return [
        "--robot.type=pusht_sim",
        f"--robot.stats_path={stats}",
        f"--robot.calibration_dir={calibration}",
        f"--robot.seed={seed}",
        f"--robot.episode_length={episode_length}",
    ]


def rollout_cmd(path: Path, robot: list[str], duration: int, rtc_threshold: int | None) -> list[str]:
    cmd = [
        lerobot_bin("lerobot-rollout"),
        *robot,
        f"--policy.path={path}",
        f"--fps={FPS}",
        f"--duration={duration}",
        "--device=cpu",
        "--return_to_initial_position=false",
    ]
    if rtc_threshold is not None:
        cmd += ["--inference.type=rtc", f"--inference.queue_threshold={rtc_threshold}"]
    return cmd


def client_cmd(path: Path, config: PreTrainedConfig, robot: list[str], port: int) -> list[str]:
    return [
        sys.executable,
        "-m",
        "lerobot.async_inference.robot_client",
        *robot,
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


def episode_over(stats: Path) -> bool:
    try:
        return bool(json.loads(stats.read_text())["episodes"])
    except (FileNotFoundError, json.JSONDecodeError):  # not written yet, or being written
        return False


def until_episode_over(run: "Logged", stats: Path, timeout: float) -> None:
    """Wait for the robot to finish its episode (or the process to end, or `timeout`), then stop it."""
    end = time.monotonic() + timeout
    while time.monotonic() < end and run.proc.poll() is None and not episode_over(stats):
        time.sleep(0.25)
    rc = run.stop()
    if not episode_over(stats):
        why = f"exited with code {rc}" if time.monotonic() < end else f"ran {timeout:.0f} s"
        raise RuntimeError(f"the episode did not end: the run {why}")


def start_episode(path: Path, config: PreTrainedConfig, engine: str, i: int, args) -> tuple:
    """Start episode i of one row: (its run, its robot's stats file, its log)."""
    name = f"{args.row_name}_{engine}_{i:03d}"
    stats = args.output_dir / "stats" / f"{name}.json"
    stats.unlink(missing_ok=True)
    robot = robot_args(stats, args.output_dir / "calibration", args.seed + i, args.episode_length)
    log = args.output_dir / "logs" / f"{name}.log"
    if engine == "async":
        return Logged(client_cmd(path, config, robot, args.port), log, CLIENT_READY), stats, log
    threshold = args.rtc_threshold if engine == "rtc" else None
    return Logged(rollout_cmd(path, robot, int(args.episode_length / FPS) + 60, threshold), log), stats, log


def finish_episode(run: "Logged", stats: Path, log: Path, args) -> dict:
    """Wait for a started episode to end; returns the robot's stats."""
    try:
        until_episode_over(run, stats, timeout=args.episode_length / FPS + 180)  # model loading included
    except RuntimeError as e:
        raise RuntimeError(f"{e}; see {log}") from None
    return json.loads(stats.read_text())


def run_episodes(path: Path, config: PreTrainedConfig, engine: str, args) -> list[dict]:
    """Every episode of one row, `args.parallel` at a time; the stats of those that finished before
    the first failure (whose error, with what finished, is in the RuntimeError raised)."""
    episodes: list[dict] = []
    for first in range(0, args.episodes, args.parallel):
        wave = [
            start_episode(path, config, engine, i, args)
            for i in range(first, min(first + args.parallel, args.episodes))
        ]
        errors = []
        for run, stats, log in wave:
            try:
                episodes.append(finish_episode(run, stats, log, args))
            except RuntimeError as e:
                errors.append(str(e))
        print(f"[deployment] {args.row_name} / {engine}: episode {len(episodes)}/{args.episodes}", flush=True)
        if errors:
            raise EpisodesError(episodes, f"episode {len(episodes) + 1}: {errors[0]}")
    return episodes


class EpisodesError(RuntimeError):
    """A row's run that stopped: the episodes that finished, and why it stopped."""

    def __init__(self, episodes: list[dict], message: str):
        super().__init__(message)
        self.episodes = episodes


def start_server(args, log: Path) -> "Logged":
    server_cmd = [
        lerobot_bin("lerobot-sdp-policy-server"),
        "--host=127.0.0.1",
        f"--port={args.port}",
        f"--fps={FPS}",
        "--session_timeout_s=5",  # one client per episode: the last one's session frees its slot soon
        f"--max_clients={2 * args.parallel}",  # a wave's clients while the last wave's sessions time out
    ]
    server = Logged(server_cmd, log)
    wait_for_port(args.port, server.proc)
    return server


def summarise(episodes: list[dict]) -> dict:
    finished = [s["episodes"][0] for s in episodes]
    jumps = [s["action_jump_px"]["p95"] for s in episodes if s["action_jump_px"]]
    return {
        **figures([e["max_reward"] for e in finished], [e["success"] for e in finished]),
        "missed_ticks_per_episode": sum(s["missed_ticks"] for s in episodes) / len(episodes),
        "missed_ticks_max": max(s["missed_ticks"] for s in episodes),
        "action_jump_p95_px_median": sorted(jumps)[len(jumps) // 2] if jumps else None,
        "episode_steps": [e["steps"] for e in finished],
    }


def measure(name: str, path: Path, engine: str, args) -> dict:
    row = {
        "policy": name,
        "path": str(path),
        "engine": engine,
        "seeds": [args.seed, args.seed + args.episodes - 1],
        "parallel": args.parallel,
    }
    config = PreTrainedConfig.from_pretrained(path)
    if engine == "rtc" and config.type != "sdp":
        return row | {
            "error": f"not run: LeRobot's `{config.type}` policy has no RTC support (supports_rtc())"
        }
    (args.output_dir / "logs").mkdir(parents=True, exist_ok=True)
    args.row_name = name
    started = time.monotonic()
    server = (
        start_server(args, args.output_dir / "logs" / f"{name}_async_server.log")
        if engine == "async"
        else None
    )
    try:
        episodes = run_episodes(path, config, engine, args)
    except EpisodesError as e:
        episodes, row["error"] = e.episodes, str(e)
    finally:
        if server is not None:
            server.stop(signal.SIGTERM)
    row["wall_s"] = round(time.monotonic() - started, 1)
    return row | (summarise(episodes) if episodes else {})


def jump_cell(row: dict) -> str:
    jump = row["action_jump_p95_px_median"]
    return "" if jump is None else f"{jump:.1f}"


# column -> its cell of a measured row; a row that could not run fills only policy, engine and note
COLUMNS = {
    "policy": lambda r: r["policy"],
    "engine": lambda r: r["engine"],
    "episodes": lambda r: r["n_episodes"],
    "avg_max_reward": lambda r: with_se(r, "avg_max_reward", 3),
    "success %": lambda r: with_se(r, "pc_success", 0),
    "missed ticks / episode (max)": lambda r: (
        f"{r['missed_ticks_per_episode']:.1f} ({r['missed_ticks_max']})"
    ),
    "target jump p95 (px, median episode)": jump_cell,
    "note": lambda r: r.get("error", ""),
}
ALWAYS = ("policy", "engine", "note")


def markdown(rows: list[dict]) -> str:
    cells = [
        [cell(r) if "avg_max_reward" in r or name in ALWAYS else "" for name, cell in COLUMNS.items()]
        for r in rows
    ]
    return "\n".join(table(list(COLUMNS), cells)) + "\n"


def run(args: argparse.Namespace) -> list[dict]:
    if args.parallel < 1 or args.episodes < 1:
        raise SystemExit(
            f"--parallel and --episodes must be at least 1, got {args.parallel} and {args.episodes}."
        )
    policies = parse_policies(args.policy)
    problems = [p for p in map(robot_ready_problem, policies.values()) if p]
    if problems:
        raise SystemExit("\n".join(problems))
    args.output_dir.mkdir(parents=True, exist_ok=True)
    let_sigint_reach_children()  # the clients are stopped with SIGINT
    rows = []
    for name, path in policies.items():
        for engine in args.engines:
            print(f"[deployment] {name} / {engine}: {args.episodes} episodes on pusht_sim", flush=True)
            rows.append(measure(name, path, engine, args))
            write_json(args.output_dir / "results.json", {"fps": FPS, "rows": rows})
    table = markdown(rows)
    (args.output_dir / "results.md").write_text(table)
    print(table)
    return rows
