"""Training throughput A/B through `lerobot-train`: samples per second under different settings.

Each variant runs the real `lerobot-train` for `--steps` steps (no evaluation, no checkpoints) with
its own environment and flags, and its throughput is read from the console the way a user sees
it: the wall-clock time between the first and the last of LeRobot's step logs (so start-up and
dataset loading are excluded), times the batch size. `--busy N` runs N busy-looping processes
beside each variant, to measure how a run degrades on a loaded machine.

Variants (`--variants`); the first four read the data with LeRobot's reader (SDP_DATA_IN_MEMORY=0),
the `memory` ones from memory (`lerobot_sdp.memory_dataset`, the default since it exists):
  baseline   the settings `configs/pusht_state_cpu.json` shipped with before the throughput work:
             no DataLoader worker, torch's default thread count (one per core);
  tuned      one DataLoader worker and one torch thread in the training process
             (OMP_NUM_THREADS=1): data loading and the update run on separate cores;
  workers2   two DataLoader workers, one torch thread (the CPU configs' setting before the data
             came from memory);
  threads2_passive  one worker, two torch threads whose OpenMP pool sleeps instead of spinning
             while it waits (OMP_WAIT_POLICY=PASSIVE);
  memory     data from memory, no worker, one torch thread per core (the CPU configs' setting now);
  memory_bf16  the same with the forward under bf16 autocast (`--policy.use_amp=true`).
Output: OUTPUT_DIR/throughput.json and a Markdown table on stdout.
"""

import argparse
import json
import os
import re
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path

from .. import memory_dataset
from ..lerobot_cli import lerobot_bin
from .curves import parse_step
from .policy_args import add_training_arguments
from .report import table, write_json

STEP_LOG = re.compile(r"step:(\d+(?:\.\d+)?[KM]?) .*updt_s:([\d.]+) data_s:([\d.]+)")
THREAD_VARS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OMP_WAIT_POLICY", memory_dataset.ENV)
READER = {memory_dataset.ENV: "0"}
ONE_THREAD = {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
CORES = str(len(os.sched_getaffinity(0)))
ALL_CORES = {"OMP_NUM_THREADS": CORES, "MKL_NUM_THREADS": CORES}
VARIANTS = {
    "baseline": (READER, ["--num_workers=0"]),
    "tuned": (READER | ONE_THREAD, ["--num_workers=1"]),
    "workers2": (READER | ONE_THREAD, ["--num_workers=2"]),
    "threads2_passive": (
        READER | {"OMP_NUM_THREADS": "2", "MKL_NUM_THREADS": "2", "OMP_WAIT_POLICY": "PASSIVE"},
        ["--num_workers=1"],
    ),
    "memory": (ALL_CORES, ["--num_workers=0"]),
    "memory_bf16": (ALL_CORES, ["--num_workers=0", "--policy.use_amp=true"]),
}


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_training_arguments(p)
    p.add_argument("--variants", nargs="+", default=["baseline", "tuned"], choices=list(VARIANTS))
    p.add_argument("--steps", type=int, default=400)
    p.add_argument("--log_freq", type=int, default=50)
    p.add_argument("--busy", type=int, default=0, help="busy-looping processes beside each run")
    p.add_argument("--extra", nargs="*", default=[], help="more lerobot-train flags for every variant")
    p.add_argument("--output_dir", type=Path, default=Path("outputs/benchmarks/throughput"))


@contextmanager
def busy_processes(n: int):
    procs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]
    try:
        yield
    finally:
        for proc in procs:
            proc.kill()
            proc.wait()


def run_variant(args: argparse.Namespace, name: str) -> dict:
    env_extra, flags = VARIANTS[name]
    env = {k: v for k, v in os.environ.items() if k not in THREAD_VARS} | env_extra
    out = args.output_dir / name
    cmd = [
        lerobot_bin("lerobot-train"),
        f"--config_path={args.config_path}",
        f"--dataset.repo_id={args.repo_id}",
        f"--dataset.root={args.dataset_root}",
        f"--steps={args.steps}",
        f"--log_freq={args.log_freq}",
        f"--save_freq={10 * args.steps}",
        "--save_checkpoint=false",
        "--env_eval_freq=0",
        "--wandb.enable=false",
        f"--output_dir={out}",
        *flags,
        *args.extra,
    ]
    marks = []  # (wall time, step, updt_s, data_s) of every step log
    log = args.output_dir / f"{name}.log"
    log.parent.mkdir(parents=True, exist_ok=True)
    print(f"[{name}] {' '.join(cmd)}", flush=True)
    with (
        busy_processes(args.busy),
        log.open("w") as f,
        subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True) as proc,
    ):
        for line in proc.stdout:
            f.write(line)
            if match := STEP_LOG.search(line):
                step, updt, data = parse_step(match[1]), float(match[2]), float(match[3])
                marks.append((time.perf_counter(), step, updt, data))
    if proc.returncode != 0 or len(marks) < 2:
        raise RuntimeError(f"lerobot-train ({name}) failed or logged fewer than 2 steps; see {log}")
    (t0, s0, *_), (t1, s1, *_) = marks[0], marks[-1]
    batch_size = json.loads(args.config_path.read_text())["batch_size"]
    steps_per_s = (s1 - s0) / (t1 - t0)
    return {
        "variant": name,
        "env": env_extra,
        "flags": flags,
        "busy_processes": args.busy,
        "steps_timed": s1 - s0,
        "steps_per_s": steps_per_s,
        "samples_per_s": steps_per_s * batch_size,
        "last_log_updt_s": marks[-1][2],
        "last_log_data_s": marks[-1][3],
        "log": str(log),
    }


def run(args: argparse.Namespace) -> None:
    rows = [run_variant(args, name) for name in args.variants]
    base = rows[0]["samples_per_s"]
    for row in rows:
        row["speedup_over_first"] = row["samples_per_s"] / base
    report = {"config_path": str(args.config_path), "rows": rows}
    write_json(args.output_dir / "throughput.json", report)
    header = ["variant", "busy procs", "samples/s", "steps/s", "x first", "updt_s", "data_s (last log)"]
    cells = [
        [
            r["variant"],
            r["busy_processes"],
            f"{r['samples_per_s']:.0f}",
            f"{r['steps_per_s']:.2f}",
            f"{r['speedup_over_first']:.2f}",
            f"{r['last_log_updt_s']:.3f}",
            f"{r['last_log_data_s']:.3f}",
        ]
        for r in rows
    ]
    print("\n".join(table(header, cells)))
