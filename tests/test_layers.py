"""The package's layers point one way: the algorithm core, then the LeRobot adapter, then tasks and
deployment, then benchmarks. A module may import its own layer and the layers below, never above; a
module this test does not place fails it too (place it in LAYERS)."""

import ast
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1] / "lerobot_sdp"
LAYERS = {
    "core": ["schedule", "geometry", "noise_schemes", "loss_weighting", "buffer", "unet", "ema"],
    "adapter": [
        "configuration_sdp",
        "modeling_sdp",
        "processor_sdp",
        "warm_start",
        "model_card",
        "torchcodec_notice",
        "dataset_writing",
        "lerobot_cli",
        "shipped_configs",
        "observations",
        "rtc",
        "chunk_cost",
        "data_parallel",
        "memory_dataset",
    ],
    "tasks": ["main_job", "robots", "pusht", "robomimic", "policy_server", "protocol_pickle"],
    "benchmarks": ["benchmarks"],
}
RANK = {top: rank for rank, tops in enumerate(LAYERS.values()) for top in tops}
ENTRY = "__init__"  # the plugin's entry point registers the adapter and the tasks' configs


def top_level(module: str) -> str:
    """`lerobot_sdp.robots.pusht_sim` -> `robots`."""
    return module.split(".")[1]


def module_name(path: Path) -> str:
    parts = path.relative_to(PKG.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imported(path: Path) -> set[str]:
    """The lerobot_sdp modules a file imports (relative imports resolved)."""
    package = module_name(path) if path.name == "__init__.py" else module_name(path).rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names if a.name.startswith("lerobot_sdp.")}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*anchor, base] if base else anchor)
            if base == "lerobot_sdp":  # `from lerobot_sdp import x` / `from . import x` at the top
                found |= {f"lerobot_sdp.{a.name}" for a in node.names}
            elif base.startswith("lerobot_sdp."):
                found.add(base)
    return found


def modules() -> list[Path]:
    return sorted(p for p in PKG.rglob("*.py") if p != PKG / f"{ENTRY}.py")


def test_every_module_has_a_layer():
    unplaced = sorted({top_level(module_name(p)) for p in modules()} - set(RANK))
    assert not unplaced, f"place these in LAYERS: {unplaced}"


@pytest.mark.parametrize("path", modules(), ids=lambda p: str(p.relative_to(PKG)))
def test_imports_point_down(path):
    here = top_level(module_name(path))
    upward = [m for m in imported(path) if top_level(m) in RANK and RANK[top_level(m)] > RANK[here]]
    assert not upward, f"{here} ({list(LAYERS)[RANK[here]]}) imports upward: {sorted(upward)}"


def test_the_entry_point_never_imports_benchmarks():
    assert not any(top_level(m) == "benchmarks" for m in imported(PKG / f"{ENTRY}.py"))


def test_the_check_sees_relative_and_absolute_imports():
    """The parser itself: an upward import written either way is found."""
    probe = PKG / "robots" / "pusht_sim.py"
    assert "lerobot_sdp.robots.config_pusht_sim" in imported(probe)
    assert "lerobot_sdp.protocol_pickle" in imported(PKG / "policy_server.py")
    assert "lerobot_sdp.main_job" in imported(PKG / "pusht" / "job.py")  # from ..main_job import


def test_the_guides_map_names_every_module_and_subpackage():
    guide = (PKG.parent / "docs" / "guide.md").read_text()
    layout = guide[guide.index("### Layout") :].split("\n### ", 1)[0]
    names = [f"`{p.name}`" for p in PKG.glob("*.py") if p.name != "__init__.py"]
    names += [f"`{p.parent.name}/`" for p in PKG.glob("*/__init__.py")]
    missing = [n for n in names if n not in layout]
    assert not missing, f"docs/guide.md's Layout does not name {missing}"
