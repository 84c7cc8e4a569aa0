"""The training configs shipped with the plugin (`configs/` of the repository), found the same from a
checkout and from an installed wheel, where they are the package data `lerobot_sdp/configs/`.

    python -m lerobot_sdp.shipped_configs                    # list them, with their paths
    lerobot-train --config_path=$(python -m lerobot_sdp.shipped_configs pusht_state_paper)
"""

import argparse
from pathlib import Path

HERE = Path(__file__).resolve().parent
# installed: package data inside the package; a checkout (editable install): the repository's configs/
ROOTS = (HERE / "configs", HERE.parent / "configs")


def root() -> Path:
    for candidate in ROOTS:
        if candidate.is_dir():
            return candidate
    raise FileNotFoundError(f"No shipped configs at {' or '.join(map(str, ROOTS))}: reinstall the plugin.")


def names() -> list[str]:
    return sorted(p.stem for p in root().glob("*.json"))


def path(name: str) -> Path:
    """The shipped config `name` (e.g. `pusht_state_cpu`, with or without `.json`)."""
    found = root() / f"{name.removesuffix('.json')}.json"
    if not found.is_file():
        raise FileNotFoundError(f"No shipped config {name!r}; the plugin ships {names()}.")
    return found


def config_argument(value: str) -> Path:
    """An argparse `type` for `--config_path`: a JSON file, or the name of a shipped config. Given as
    the default by name, it resolves only when the command runs."""
    given = Path(value)
    if given.suffix == ".json" or given.exists():
        return given
    try:
        return path(value)
    except FileNotFoundError as e:
        raise argparse.ArgumentTypeError(f"{e} Pass a config file or one of those names.") from None


def main(argv: list[str] | None = None) -> None:
    raw = argparse.RawDescriptionHelpFormatter
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=raw)
    parser.add_argument("name", nargs="?", help="print this config's path (default: list them all)")
    args = parser.parse_args(argv)
    try:
        print(path(args.name) if args.name else "\n".join(f"{n}\t{path(n)}" for n in names()))
    except FileNotFoundError as e:
        raise SystemExit(f"error: {e}") from None


if __name__ == "__main__":
    main()
