"""The ``hktex`` command line.

Each subcommand lives in its own module named ``cmd_<name>.py`` in this package (engine
commands) or in ``hktex_server.cli`` (serve, worker, demo) and exposes
``register(subparsers) -> None``, found through the ``hktex.commands`` entry-point group of
``pyproject.toml`` (so the engine names no module of the service); the parser's ``func`` default is the handler, which takes the
parsed ``argparse.Namespace`` and returns a JSON-able summary dict. This module gives every
command the same contract (INTERFACES.md section 3): ``--json`` prints a one-line summary on
stdout, bad input exits non-zero with one line on stderr, a terminal shows a progress bar.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from importlib.metadata import entry_points
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hktex_engine.errors import HKTexError, TooManyVerticesError
from hktex_engine.spectra.cores import cpu_sample

if TYPE_CHECKING:
    from hktex_engine.kernels.model import KernelSet
    from hktex_engine.spectra.grid import Spectra


class TerminalProgress:
    """A tqdm bar on a terminal, silence elsewhere; implements ``progress.Progress``."""

    def __init__(self, desc: str, enabled: bool | None = None) -> None:
        self.desc = desc
        self.enabled = sys.stderr.isatty() if enabled is None else enabled
        self._bar = None

    def update(self, step: int, total: int, **metrics: Any) -> None:
        if not self.enabled:
            return
        if self._bar is None:
            from tqdm import tqdm

            self._bar = tqdm(total=total, desc=self.desc, file=sys.stderr, leave=False)
        self._bar.total = total
        self._bar.n = step
        shown = {k: f"{v:.4g}" if isinstance(v, float) else v for k, v in metrics.items()}
        self._bar.set_postfix(shown, refresh=False)
        self._bar.refresh()

    def should_stop(self) -> bool:
        return False

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None


def add_max_vertices(parser: argparse.ArgumentParser) -> None:
    """``--max-vertices``, the same on every command that reads a mesh file, so a mesh the
    spectra were made for can also be fitted and baked."""
    from hktex_engine.geometry.mesh import DEFAULT_MAX_VERTICES

    parser.add_argument(
        "--max-vertices",
        type=int,
        default=DEFAULT_MAX_VERTICES,
        help=f"refuse meshes with more vertices after merging ({DEFAULT_MAX_VERTICES:,})",
    )


def load_kernelset_with_spectra(kernels: Path, spectra_dir: Path) -> tuple[Spectra, KernelSet]:
    """The spectra and a kernel set checked to belong to them (same mesh, same grid): where
    ``render``, ``bake`` and ``query`` all start."""
    from hktex_engine.kernels.hkt import load_hkt
    from hktex_engine.spectra.grid import load_spectra

    if not kernels.is_file():
        raise FileNotFoundError(f"kernel-set file not found: {kernels}")
    spectra = load_spectra(spectra_dir)
    kernelset = load_hkt(
        kernels, expect_mesh_hash=spectra.mesh_hash, expect_config_hash=spectra.config_hash
    )
    return spectra, kernelset


def _command_registrars() -> list[Callable[[Any], None]]:
    """Every installed ``hktex.commands`` entry point, in name order: the engine's commands and
    whatever else is installed beside it (the service adds serve, worker and demo)."""
    found = sorted(entry_points(group="hktex.commands"), key=lambda ep: ep.name)
    return [ep.load() for ep in found]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="hktex", description="Heat Kernel Textures")
    parser.add_argument("--json", action="store_true", help="print a one-line JSON summary")
    sub = parser.add_subparsers(dest="command", required=True)
    for register in _command_registrars():
        register(sub)
    for subparser in sub.choices.values():  # `hktex CMD ... --json` works as well
        subparser.add_argument(
            "--json", action="store_true", default=argparse.SUPPRESS, help=argparse.SUPPRESS
        )
    return parser


def main(argv: list[str] | None = None) -> int:
    # the machine's CPU counters before anything heavy: ``hktex spectra`` counts the cores
    # others keep busy over the time it spends importing and loading the mesh anyway, which
    # it cannot do from a sample taken after its imports (sampled at its registration, the
    # window was 0.07 s by the time it asked, so it slept 0.18 s of a 4 s command)
    started = cpu_sample()
    parser = build_parser()
    args = parser.parse_args(argv)
    args.cpu_since = started
    try:
        summary = args.func(args)
    except (HKTexError, FileNotFoundError, ValueError) as exc:
        message = " ".join(str(exc).split()) or type(exc).__name__
        if isinstance(exc, TooManyVerticesError) and hasattr(args, "max_vertices"):
            message += " (raise it with --max-vertices)"
        print(f"hktex {args.command}: error: {message}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"hktex {args.command}: interrupted", file=sys.stderr)
        return 130
    if summary is not None:
        if args.json:
            print(json.dumps(summary, separators=(",", ":"), default=str))
        elif isinstance(summary, dict) and summary.get("message"):
            print(summary["message"])
    return 0


if __name__ == "__main__":
    sys.exit(main())
