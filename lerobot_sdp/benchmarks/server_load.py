"""Policy-server load: how many clients at 10 Hz one machine serves before a client misses a tick.

    lerobot-sdp-bench server-load --policy sdp=PATH/pretrained_model --clients 1 2 3 4 6 8 \\
        --output_dir outputs/benchmarks/server_load

For each N of `--clients`: `lerobot-sdp-policy-server` (the real CLI, `--max_clients=N`), then N
LeRobot `RobotClient`s, each with its own connection (hence its own session) and its own `pusht_sim`
(Push-T at 10 Hz in real time: a tick without an action holds the last target and counts as missed),
set up one after the other and started together. Client i runs the episode seeded `--seed` + i for
`--episode_length` ticks (or until it succeeds). Per N: missed ticks per client (mean and max), the
longest gap between two actions of any client, avg_max_reward. The clients run in one process on the
same machine as the server, so their CPU counts against it: a conservative figure for a server whose
clients are robots elsewhere. Output: OUTPUT_DIR/results.json (after every N), results.md; the
server's console in OUTPUT_DIR/logs/. Run it as the only heavy process on the machine.
"""

import argparse
import signal
import statistics
import threading
import time
from pathlib import Path

import grpc
from lerobot.configs.policies import PreTrainedConfig

from ..lerobot_cli import lerobot_bin
from ..pusht.evaluation import EVAL_SEED
from ..robots import PushTSimConfig
from .deployment import FPS, Logged, robot_ready_problem, wait_for_port
from .policy_args import add_policy_argument, parse_policies
from .report import table, write_json


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_policy_argument(p)
    p.add_argument("--clients", nargs="+", type=int, default=[1, 2, 3, 4, 6, 8], help="client counts")
    p.add_argument("--seed", type=int, default=EVAL_SEED, help="client i's episode starts from seed + i")
    p.add_argument("--episode_length", type=int, default=200, help="ticks per episode")
    p.add_argument("--port", type=int, default=8081, help="the policy server's port (loopback)")
    p.add_argument("--output_dir", type=Path, default=Path("outputs/benchmarks/server_load"))


def make_client(path: Path, config: PreTrainedConfig, seed: int, args, calibration: Path):
    """A LeRobot RobotClient on its own connection: clients in one process otherwise share one, and the
    server (which tells clients apart by connection) would serve them as one."""
    from lerobot.async_inference.configs import RobotClientConfig
    from lerobot.async_inference.robot_client import RobotClient
    from lerobot.transport import services_pb2_grpc
    from lerobot.transport.utils import grpc_channel_options

    robot = PushTSimConfig(calibration_dir=calibration, seed=seed, episode_length=args.episode_length)
    client = RobotClient(
        RobotClientConfig(
            policy_type=config.type,
            pretrained_name_or_path=str(path),
            robot=robot,
            actions_per_chunk=2 * config.n_action_steps,
            server_address=f"127.0.0.1:{args.port}",
            fps=FPS,
        )
    )
    client.channel.close()
    options = grpc_channel_options(initial_backoff=f"{1 / FPS:.4f}s")
    client.channel = grpc.insecure_channel(
        client.server_address, [*options, ("grpc.use_local_subchannel_pool", 1)]
    )
    client.stub = services_pb2_grpc.AsyncInferenceStub(client.channel)
    return client


def drive(clients: list, timeout_s: float) -> None:
    """Start every client's two threads (as LeRobot's `async_client` does) at once; stop them all
    when every robot's episode is over."""
    threads = []
    for client in clients:
        threads += [
            threading.Thread(target=client.receive_actions, daemon=True),
            threading.Thread(target=client.control_loop, kwargs={"task": ""}, daemon=True),
        ]
    for thread in threads:
        thread.start()
    end = time.monotonic() + timeout_s
    while time.monotonic() < end and not all(c.robot.episodes for c in clients):
        time.sleep(0.25)
    for client in clients:
        client.shutdown_event.set()
    for thread in threads:
        thread.join(timeout=10)


def one_load(path: Path, config: PreTrainedConfig, n: int, args) -> dict:
    log = args.output_dir / "logs" / f"server_{n}_clients.log"
    server_cmd = [
        lerobot_bin("lerobot-sdp-policy-server"),
        "--host=127.0.0.1",
        f"--port={args.port}",
        f"--fps={FPS}",
        f"--max_clients={n}",
    ]
    server = Logged(server_cmd, log)
    clients = []
    try:
        wait_for_port(args.port, server.proc)
        for i in range(n):
            client = make_client(path, config, args.seed + i, args, args.output_dir / "calibration" / str(i))
            if not client.start():
                raise RuntimeError(f"client {i} could not set up its policy; see {log}")
            clients.append(client)
        started = time.monotonic()
        drive(clients, timeout_s=args.episode_length / FPS + 60)
        wall = time.monotonic() - started
        stats = [c.robot.stats() for c in clients]
    finally:
        for client in clients:
            client.stop()
        server.stop(signal.SIGTERM)
    over = [s["episodes"][0] for s in stats if s["episodes"]]
    return {
        "clients": n,
        "episodes_over": len(over),
        "missed_ticks_mean": statistics.fmean(s["missed_ticks"] for s in stats),
        "missed_ticks_max": max(s["missed_ticks"] for s in stats),
        "ticks_mean": statistics.fmean(e["steps"] for e in over) if over else None,
        "longest_gap_s": max(s["longest_gap_s"] for s in stats),
        "avg_max_reward": statistics.fmean(e["max_reward"] for e in over) if over else None,
        "wall_s": round(wall, 1),
    }


def markdown(name: str, rows: list[dict]) -> str:
    header = [
        "clients",
        "missed ticks per client (max)",
        "longest gap between actions (s)",
        "ticks per episode",
        "avg_max_reward",
    ]
    cells = [
        [
            r["clients"],
            f"{r['missed_ticks_mean']:.1f} ({r['missed_ticks_max']})",
            f"{r['longest_gap_s']:.2f}",
            f"{r['ticks_mean']:.0f}",
            f"{r['avg_max_reward']:.3f}",
        ]
        for r in rows
    ]
    return "\n".join([f"Policy `{name}`, {FPS} Hz.", "", *table(header, cells)]) + "\n"


def run(args: argparse.Namespace) -> dict:
    policies = parse_policies(args.policy)
    if len(policies) != 1:
        raise SystemExit("server-load takes one --policy NAME=PATH.")
    ((name, path),) = policies.items()
    problem = robot_ready_problem(path)
    if problem:
        raise SystemExit(problem)
    if any(n < 1 for n in args.clients):
        raise SystemExit(f"--clients must be at least 1, got {args.clients}.")
    config = PreTrainedConfig.from_pretrained(path)
    (args.output_dir / "logs").mkdir(parents=True, exist_ok=True)
    result = {"policy": name, "path": str(path), "fps": FPS, "episode_length": args.episode_length}
    result["rows"] = []
    for n in args.clients:
        print(f"[server-load] {n} clients", flush=True)
        result["rows"].append(one_load(path, config, n, args))
        write_json(args.output_dir / "results.json", result)
    table = markdown(name, result["rows"])
    (args.output_dir / "results.md").write_text(table)
    print(table)
    return result
