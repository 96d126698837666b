"""Code widths of a quantised ``.hkt`` chosen for the fit they store.

Why per fit: quantisation noise adds to the fit's own error (they are independent), so what
it costs depends on how good the fit is: the format's default widths (``QUANT_BITS``) keep
the quantised albedo ~58-60 dB from the exact one, which a 42 dB fit needs, but on a 33 dB fit
the same 0.1 dB allows noise ~10x larger. :func:`choose_bits` walks a ladder of widths from
the default to narrow ones and keeps the narrowest whose quantised set, decoded as a reader
would, scores within ``budget_db`` of the exact set against the fit's own target (surface
PSNR on points drawn for the purpose, not the evaluation points), so the file is as small as
that fit's accuracy allows. The reader needs nothing new: the widths are in the file's
quantisation table.
"""

from __future__ import annotations

import io

import numpy as np

from hktex_engine.evaluation.metrics import psnr
from hktex_engine.kernels.hkt import QUANT_BITS, encode_hkt, load_hkt, sorted_by_face
from hktex_engine.kernels.model import KernelSet

#: Widths from the format's default to narrow ones. Each step narrows the members that cost
#: least first: measured one member at a time on the fitted spot set (2,216 kernels, 33.6 dB;
#: benchmarks/results/hkt_quantised_ladder.md), colours cost most (7 bits alone: -0.06 dB,
#: 6 bits: -0.29), the geometry little (barycentrics 7: -0.02, theta and eta 6: -0.01 each,
#: threshold 9: 0, sharpness 5: -0.02), so colours narrow only in the last steps.
BITS_LADDER: tuple[dict[str, int], ...] = (
    dict(QUANT_BITS),
    {"barycentrics": 7, "theta": 7, "eta": 7, "threshold": 10, "sharpness": 6, "colors": 8},
    {"barycentrics": 7, "theta": 6, "eta": 6, "threshold": 9, "sharpness": 5, "colors": 8},
    {"barycentrics": 6, "theta": 6, "eta": 5, "threshold": 9, "sharpness": 5, "colors": 8},
    {"barycentrics": 6, "theta": 6, "eta": 5, "threshold": 8, "sharpness": 5, "colors": 7},
    {"barycentrics": 5, "theta": 5, "eta": 4, "threshold": 8, "sharpness": 4, "colors": 7},
)
#: Widths above the default, tried in turn when even the default loses more than the budget
#: (fits near 39 dB and above: the full default on spot lost 0.34 dB at the default widths,
#: colours first, then the geometry).
WIDER_LADDER: tuple[dict[str, int], ...] = (
    {"barycentrics": 8, "theta": 8, "eta": 8, "threshold": 10, "sharpness": 8, "colors": 10},
    {"barycentrics": 10, "theta": 9, "eta": 9, "threshold": 11, "sharpness": 9, "colors": 10},
    {"barycentrics": 11, "theta": 10, "eta": 10, "threshold": 12, "sharpness": 10, "colors": 12},
    {"barycentrics": 13, "theta": 12, "eta": 12, "threshold": 14, "sharpness": 12, "colors": 14},
)
#: Surface PSNR a quantised file may lose against the exact set on the choice's points (the
#: issue's budget is 0.1 dB on the evaluation points; 0.02 dB is left for the difference).
BUDGET_DB = 0.08


def roundtrip(kernelset: KernelSet, bits: dict[str, int] | None) -> tuple[KernelSet, int]:
    """The set as a reader gets it back from a quantised file with ``bits``, and the file's
    bytes (the set sorted by face, as the file stores it)."""
    payload = encode_hkt(kernelset, True, quantised=True, bits=bits)
    return load_hkt(io.BytesIO(payload)), len(payload)


def choose_bits(
    spectra,
    kernelset: KernelSet,
    face_ids: np.ndarray,
    bary: np.ndarray,
    target: np.ndarray,
    budget_db: float = BUDGET_DB,
) -> dict:
    """The narrowest :data:`BITS_LADDER` widths within ``budget_db`` of the exact set's
    surface PSNR at ``(face_ids, bary)`` against ``target``; when even the default widths are
    not, the first :data:`WIDER_LADDER` step that is (its widest step when none is). Returns ``{"bits", "bytes", "psnr", "kernelset", "psnr_exact",
    "budget_db", "tried"}``; ``kernelset`` is the chosen file's set as a reader gets it."""
    from hktex_engine.kernels.query import AlbedoQuery

    def score(ks: KernelSet) -> float:
        return psnr(AlbedoQuery(spectra, ks, device="cpu").colors(face_ids, bary), target)

    exact = score(sorted_by_face(kernelset))
    tried = []
    chosen = None
    for bits in BITS_LADDER:
        q, nbytes = roundtrip(kernelset, bits)
        value = score(q)
        tried.append({"bits": bits, "bytes": nbytes, "psnr": value})
        if exact - value > budget_db:
            break
        chosen = {**tried[-1], "kernelset": q}
    if chosen is None:
        for bits in WIDER_LADDER:
            q, nbytes = roundtrip(kernelset, bits)
            tried.append({"bits": bits, "bytes": nbytes, "psnr": score(q)})
            chosen = {**tried[-1], "kernelset": q}
            if exact - tried[-1]["psnr"] <= budget_db:
                break
    return {**chosen, "psnr_exact": exact, "budget_db": budget_db, "tried": tried}
