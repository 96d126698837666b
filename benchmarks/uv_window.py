"""The worst UV window of a fitted set, and the same window of other sets, side by side.

    python benchmarks/uv_window.py --mesh blub --sets A.hkt B.hkt -o eyes.png [--width 224]

A whole-texture error map (``fidelity.py --pictures``) shows where a set is wrong; this zooms
in: the 224-texel window (of a 1024² bake in the mesh's own UV layout) around the texel where
the **first** set's error is largest, then for every set one row ``original | bake | error``
(the error as ``render.errormap``'s heat colours, the fidelity pictures' scale). Prints each
set's RMS error over the window's covered texels as JSON. Sets may use any blend or scale
(they are read with ``load_hkt``, evaluated with the product's model), so a per-kernel-sigma
set and a §4-5 set of the same mesh can be compared where it matters (blub's eyes:
docs/fitting.md, fourteenth and fifteenth passes).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

from hktex_engine.fitting.uv import evaluate_albedo
from hktex_engine.kernels.hkt import load_hkt
from hktex_engine.kernels.model import HeatKernelModel
from hktex_engine.render.bake import rasterize_uv
from hktex_engine.render.errormap import DEFAULT_SCALE, heat_colors, resample_texture
from hktex_engine.spectra.interpolation import SpectralField

#: Bake size and the stride of the search for the worst texel (every 4th texel each way).
SIZE = 1024
STRIDE = 4


def window_rows(mesh, field, sets: list[Path], width: int) -> tuple[np.ndarray, list[float]]:
    """The strip (rows of ``original | bake | error``) and each set's window RMS."""
    face_img, bary_img = rasterize_uv(np.asarray(mesh.corner_uvs, np.float64), SIZE, SIZE)
    ref = resample_texture(mesh.texture, SIZE)
    covered = face_img >= 0
    models = [HeatKernelModel.from_kernelset(load_hkt(s), field) for s in sets]
    ys, xs = np.nonzero(covered[::STRIDE, ::STRIDE])
    ys, xs = ys * STRIDE, xs * STRIDE
    pred = evaluate_albedo(models[0], face_img[ys, xs], bary_img[ys, xs])
    worst = int(np.argmax(((pred - ref[ys, xs]) ** 2).sum(1)))
    y0, x0 = (max(0, int(c) - width // 2) for c in (ys[worst], xs[worst]))
    win = (slice(y0, y0 + width), slice(x0, x0 + width))
    c = covered[win]
    rows, rms = [], []
    for m in models:
        img = ref[win].copy()
        img[c] = evaluate_albedo(m, face_img[win][c], bary_img[win][c])
        err = np.where(c, np.sqrt(((img - ref[win]) ** 2).mean(-1)), 0.0)
        rms.append(float(np.sqrt((err[c] ** 2).mean())))
        rows.append(np.concatenate([ref[win], img, heat_colors(err / DEFAULT_SCALE)], axis=1))
    return np.concatenate(rows), rms


def main() -> int:
    sys.path.insert(0, str(Path(__file__).parent))
    from fidelity import add_mesh_file_argument, named_mesh_and_spectra

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--mesh", required=True, help="a shared mesh or a --mesh-file name")
    add_mesh_file_argument(ap)
    ap.add_argument("--sets", type=Path, nargs="+", required=True, help=".hkt files")
    ap.add_argument("-o", "--output", type=Path, required=True, help="PNG to write")
    ap.add_argument("--width", type=int, default=224, help="window side in texels")
    ap.add_argument("--k", type=int, default=128, help="the sets' spectra K")
    args = ap.parse_args()

    from PIL import Image

    mesh, spectra = named_mesh_and_spectra(args.mesh_file, args.mesh, args.k)
    field = SpectralField(spectra, device="cpu", dtype=torch.float32)
    strip, rms = window_rows(mesh, field, args.sets, args.width)
    im = Image.fromarray(np.round(np.clip(strip, 0, 1) * 255).astype(np.uint8))
    im.resize((im.width * 2, im.height * 2), Image.NEAREST).save(args.output)
    print(json.dumps({"output": str(args.output), "sets": [str(s) for s in args.sets], "window_rms": rms}))  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
