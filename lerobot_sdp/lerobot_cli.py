"""Driving LeRobot's own CLIs (`lerobot-train`, `lerobot-eval`) as subprocesses, resumably.

The main job and the quality benchmark train and evaluate exactly the way a user does, so what they
report is what `lerobot-train` / `lerobot-eval` produce. A run directory is never deleted here: a
finished training run is reused, an interrupted one resumes from its last checkpoint.
"""

import json
import os
import signal
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path


class CLIError(RuntimeError):
    pass


def lerobot_bin(name: str) -> str:
    """A console script of the running environment (the venv's, not whatever is first on PATH)."""
    return str(Path(sys.executable).parent / name)


# One torch thread per LeRobot process unless the caller chose otherwise: with DataLoader workers
# beside it, data loading and the update each get a core of a small machine, and no OpenMP pool
# spin-waits for a core another process holds (docs/benchmarks.md, "Training throughput").
THREAD_DEFAULTS = {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
CHILD_GRACE_S = 30.0  # how long a child gets to stop after each signal (`end_child`)
LEROBOT_NUM_WORKERS = 4  # TrainPipelineConfig's default


def subprocess_env(threads: int = 1) -> dict[str, str]:
    """The environment of a LeRobot child: `threads` torch threads unless the user exported a count.
    One exported count sets the other too: OpenMP's pool and MKL's are both torch's, and a pool left at
    `threads` beside a user's `OMP_NUM_THREADS=1` oversubscribes the cores the user divided."""
    exported = [os.environ[name] for name in THREAD_DEFAULTS if name in os.environ]
    count = exported[0] if exported else str(threads)
    return {name: count for name in THREAD_DEFAULTS} | dict(os.environ)


def command_setting(train_args: list[str], key: str, default=None):
    """A setting of a `lerobot-train` command line (`key` dotted, e.g. "policy.device"): its flag, else
    its config file's value, else `default`. A flag's value is the string the user typed."""
    flags = dict(a.removeprefix("--").split("=", 1) for a in train_args if a.startswith("--") and "=" in a)
    if key in flags:
        return flags[key]
    node = json.loads(Path(flags["config_path"]).read_text()) if "config_path" in flags else {}
    for part in key.split("."):
        if not isinstance(node, dict) or part not in node:
            return default
        node = node[part]
    return node


def num_workers(train_args: list[str]) -> int:
    """The DataLoader workers a `lerobot-train` command line asks for: its `--num_workers`, else its
    config file's, else LeRobot's default."""
    return int(command_setting(train_args, "num_workers", LEROBOT_NUM_WORKERS))


# bf16 autocast where the CPU multiplies bf16 natively: 0.75x float32's training step on a Zen 4
# (avx512_bf16), the same loss (docs/benchmarks.md); float32 elsewhere, which has no bf16 arithmetic.
NATIVE_BF16_FLAGS = ("avx512_bf16", "amx_bf16")
PRECISIONS = ("auto", "fp32", "bf16")


def native_bf16_flag(cpuinfo: Path = Path("/proc/cpuinfo")) -> str | None:
    """The CPU flag by which this machine computes bf16 natively (Linux's cpuinfo), or None."""
    try:
        lines = cpuinfo.read_text().splitlines()
    except OSError:  # not Linux
        return None
    present = {flag for line in lines if line.startswith("flags") for flag in line.split(":", 1)[1].split()}
    return next((flag for flag in NATIVE_BF16_FLAGS if flag in present), None)


def precision_flags(train_args: list[str], precision: str = "auto") -> tuple[list[str], str]:
    """The `--policy.use_amp` flag a training gets, and why. `bf16` / `fp32` choose; `auto` turns bf16
    autocast on for a training on a CPU with native bf16 (`--policy.device=cpu`), and leaves a command
    line or config that sets use_amp itself, or a training on another device, as it is."""
    if precision != "auto":
        return [f"--policy.use_amp={str(precision == 'bf16').lower()}"], f"{precision}, as asked"
    if command_setting(train_args, "policy.use_amp") is not None:
        return [], "use_amp as the command line or config sets it"
    if command_setting(train_args, "policy.device") != "cpu":
        return [], "LeRobot's default: the training names no CPU device"
    flag = native_bf16_flag()
    if flag is None:
        return [], "fp32: this CPU has no native bf16"
    return ["--policy.use_amp=true"], f"bf16 autocast: this CPU computes bf16 natively ({flag})"


def training_threads(train_args: list[str], concurrent: int = 1) -> int:
    """One torch thread beside DataLoader workers (they hold the other cores); without them, the cores
    shared among the `concurrent` trainings that run at once: a dataset served from memory
    (`memory_dataset`) leaves every core to the updates."""
    if num_workers(train_args) > 0:
        return 1
    return max(1, len(os.sched_getaffinity(0)) // concurrent)


def let_sigint_reach_children() -> None:
    """A process that a shell starts in the background (`cmd &`, nohup) inherits SIGINT ignored, and so
    would its children: Python then installs no KeyboardInterrupt, and a LeRobot client stopped with
    SIGINT (as Ctrl-C stops it) runs on. Catching SIGINT here gives children the default disposition
    back (exec resets caught signals), so Ctrl-C and our SIGINT stop them. Call from the main thread."""
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)


def run_logged(cmd: list[str], log: Path, echo: bool = True, threads: int = 1) -> None:
    """Run a command with `threads` torch threads, echoing its output and appending it to `log`."""
    log.parent.mkdir(parents=True, exist_ok=True)
    env = subprocess_env(threads)
    threads_line = f"[threads] OMP_NUM_THREADS={env['OMP_NUM_THREADS']}"
    print(f"[run] {' '.join(cmd)}\n[log] {log}\n{threads_line}", flush=True)
    with (
        log.open("a") as f,
        subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env) as proc,
    ):
        try:
            for line in proc.stdout:
                if echo:
                    sys.stdout.write(line)
                f.write(line)
        except BaseException as error:
            # this process stops waiting (an error, Ctrl-C, a test's time limit): the child must not run
            # on unwatched, nor hold this process in Popen's exit, which waits for it
            end_child(proc, interrupted=isinstance(error, KeyboardInterrupt))
            raise
    if proc.returncode != 0:
        raise CLIError(f"{Path(cmd[0]).name} failed (exit {proc.returncode}); see {log}")


def end_child(proc: subprocess.Popen, interrupted: bool = False, grace_s: float = CHILD_GRACE_S) -> None:
    """Stop a child nobody waits for any more: SIGTERM (torchrun passes it on to its ranks), then
    SIGKILL, `grace_s` apart. After Ctrl-C, which reached the child too, it first gets `grace_s` to
    stop by itself."""
    for send in ([None] if interrupted else []) + [proc.terminate, proc.kill]:
        if send is not None:
            send()
        try:
            proc.wait(grace_s)
            return
        except subprocess.TimeoutExpired:
            continue


def last_checkpoint(train_dir: Path) -> Path:
    return train_dir / "checkpoints" / "last"


def trained_steps(train_dir: Path) -> int:
    """Optimizer steps of the newest checkpoint (0 when there is none)."""
    state = last_checkpoint(train_dir) / "training_state" / "training_step.json"
    return json.loads(state.read_text())["step"] if state.exists() else 0


def trained_precision(model_dir: Path) -> str:
    """The precision a saved policy was trained (and is evaluated) in: its config's use_amp."""
    return "bf16 autocast" if json.loads((model_dir / "config.json").read_text()).get("use_amp") else "fp32"


def train_command(processes: int = 1) -> list[str]:
    """`lerobot-train`, or with several processes the same script under torchrun (data parallel on
    one machine; `--standalone` picks a free port, so that two runs can share a machine)."""
    if processes == 1:
        return [lerobot_bin("lerobot-train")]
    launch = [lerobot_bin("torchrun"), "--standalone", f"--nproc_per_node={processes}"]
    return [*launch, "-m", "lerobot.scripts.lerobot_train"]


def train(
    train_dir: Path,
    args: list[str],
    steps: int,
    log: Path,
    echo: bool = True,
    processes: int = 1,
    concurrent: int = 1,
    precision: str | None = None,
) -> Path:
    """`lerobot-train ARGS --steps=STEPS --output_dir=TRAIN_DIR` on `processes` processes, resumed or
    skipped when a checkpoint exists, its torch threads shared with `concurrent - 1` other trainings
    that run at once, at `precision` (`precision_flags`; None: as ARGS and the config say; a resumed run
    keeps its own). Returns the final pretrained_model directory. `echo=False`: the output goes to `log`
    only."""
    model_dir = last_checkpoint(train_dir) / "pretrained_model"
    done = trained_steps(train_dir)
    if done >= steps:
        print(f"[train] {train_dir}: finished ({done} steps), reusing it", flush=True)
        return model_dir
    if done > 0:
        print(f"[train] {train_dir}: resuming at step {done}/{steps}", flush=True)
        cmd = [*train_command(processes), f"--config_path={model_dir / 'train_config.json'}", "--resume=true"]
    elif train_dir.exists():
        raise CLIError(f"{train_dir} exists but holds no checkpoint: move it away or delete it, then rerun.")
    else:
        amp, why = precision_flags(args, precision) if precision else ([], "as ARGS and the config say")
        print(f"[precision] {why}", flush=True)
        cmd = [*train_command(processes), *args, *amp, f"--steps={steps}", f"--output_dir={train_dir}"]
    run_logged(cmd, log, echo, threads=training_threads(cmd, concurrent) if processes == 1 else 1)
    return model_dir


def eval_flags(
    env: list[str], n_episodes: int, batch_size: int, device: str, seed: int, episode_length: int | None
) -> list[str]:
    """`lerobot-eval` flags for `n_episodes` from `seed` on batched sync envs (async env workers only
    compete with the policy for a small machine's cores); `env` names the environment."""
    length = [f"--env.episode_length={episode_length}"] if episode_length else []
    return [
        *env,
        *length,
        f"--eval.n_episodes={n_episodes}",
        f"--eval.batch_size={min(n_episodes, batch_size)}",
        "--eval.use_async_envs=false",
        f"--policy.device={device}",
        f"--seed={seed}",
    ]


def eval_info(eval_dir: Path) -> Path:
    """The results file of a finished `lerobot-eval` run (its presence means finished)."""
    return eval_dir / "eval_info.json"


def evaluate(model_dir: Path, eval_dir: Path, args: list[str], log: Path, echo: bool = True) -> dict:
    """`lerobot-eval --policy.path=MODEL_DIR ARGS --output_dir=EVAL_DIR`, skipped when its
    eval_info.json exists. Returns the overall metrics."""
    info = eval_info(eval_dir)
    if not info.exists():
        cmd = [lerobot_bin("lerobot-eval"), f"--policy.path={model_dir}", *args, f"--output_dir={eval_dir}"]
        run_logged(cmd, log, echo)
    return json.loads(info.read_text())["overall"]


@dataclass(frozen=True)
class Evaluation:
    """One `lerobot-eval` run for `evaluate_all`: `evaluate`'s arguments."""

    model_dir: Path
    eval_dir: Path
    args: list[str]
    log: Path


def evaluate_all(evaluations: list[Evaluation], jobs: int = 1, echo: bool = True) -> None:
    """Every evaluation (those already done skipped), `jobs` at once: each `lerobot-eval` runs one
    torch thread, so on a machine with no training running, two fill a 2-core CPU. In parallel,
    their output goes to their log files only."""

    def run(e: Evaluation) -> None:
        evaluate(e.model_dir, e.eval_dir, e.args, e.log, echo and jobs == 1)

    with ThreadPoolExecutor(max_workers=jobs) as pool:
        list(pool.map(run, evaluations))  # a failed evaluation stops the benchmark with its error
