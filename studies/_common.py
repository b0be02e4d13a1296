"""What the studies share, defined once: law labels, the edge-length signal, figure saving and copying, CLI options.

Success and settling are not here: they come from :func:`ee_formation_env.baselines.metrics.settle`
through :func:`ee_formation_env.baselines.metrics.run_episode`, the one episode loop of every study.
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from ee_formation_env.baselines import REFERENCE_CONTROLLERS
from ee_formation_env.baselines.atomic_files import replacing
from ee_formation_env.env import FormationEnv

#: The paper's laws I, II and III by label, each the name of its reference controller (registry order).
LAWS: dict[str, str] = dict(zip(("law-I", "law-II", "law-III"), REFERENCE_CONTROLLERS))
DPI = 100  # dots per inch of the studies' PNG figures


def max_edge_length_error(env: FormationEnv) -> float:
    """Largest ``| |z_k| - d_k |`` over the edges (m) at the current end-effector positions (distance formations).

    A per-step signal for tables and figures; success is decided by the formation error
    (:func:`ee_formation_env.baselines.metrics.settle`), not by this.
    """
    z = env.graph.edge_vectors(env.end_effector_positions()[:, :env.dim])
    return float(np.max(np.abs(np.linalg.norm(z, axis=1) - env.formation.desired)))


def save_figure(fig: Any, path: Path, dpi: int = DPI) -> Path:
    """Lay out ``fig``, write it as an (optimized) PNG to ``path``, close it; returns ``path``."""
    import matplotlib.pyplot as plt  # the "figures" extra: imported only by studies that draw

    fig.tight_layout()
    try:
        with replacing(path) as temporary:  # whole or not at all
            fig.savefig(temporary, dpi=dpi, format=Path(path).suffix.lstrip(".") or "png",
                        pil_kwargs={"optimize": True})
    finally:
        plt.close(fig)
    return path


def copy_figures(paths: Iterable[Path], directory: Path | None) -> list[Path]:
    """Copy each file of ``paths`` into ``directory`` (created if missing; nothing if None); the copies' paths."""
    if directory is None:
        return []
    directory.mkdir(parents=True, exist_ok=True)
    copies = []
    for path in paths:
        copies.append(Path(shutil.copy2(path, directory / Path(path).name)))
    return copies


def report_outputs(out: Path, copies: Sequence[Path] = ()) -> str:
    """Print (and return) where a study wrote: its output folder with its file count and size, and the figures
    copied elsewhere."""
    files = [path for path in Path(out).rglob("*") if path.is_file()]
    size = sum(path.stat().st_size for path in files) / 1e6
    lines = [f"wrote {len(files)} files ({size:.1f} MB) to {Path(out).resolve()}"]
    if copies:
        lines.append(f"copied {len(copies)} figures to {Path(copies[0]).parent.resolve()}")
    text = "\n".join(lines)
    print(text, flush=True)
    return text


def add_output_arguments(parser: argparse.ArgumentParser, studies: Sequence[str], default_out: str) -> None:
    """The options every figure-writing study takes: ``--out``, ``--figures-dir`` and ``--only``."""
    parser.add_argument("--out", type=Path, default=Path(default_out), help=f"output folder (default {default_out})")
    parser.add_argument("--figures-dir", type=Path, default=None, help="also copy the PNGs here")
    parser.add_argument("--only", action="append", choices=studies, help="run only this study (repeatable)")
