"""Kernel evaluation benchmark: query throughput, KNN backends, memory for a million points.

    python benchmarks/kernels.py [--kernels 10000] [--queries 100000] [--million 1000000]

Setup: a torus of ~10k vertices with the reference grid shape (7 angles x 7 anisotropies,
K = 256 eigenpairs per node, K_iso = 65). The grid's eigenvectors are random numbers of the
right shape and scale (computing 49 real K = 256 bases would take many minutes of the shared
CPU, and the cost of an evaluation does not depend on the values); the isotropic spectrum,
hence the biharmonic embedding the KNN searches, is real. Kernels: 10k random centres with
random attributes in their ranges, reference K_s = 100, K_c = 10.

Writes benchmarks/results/kernels.json and .md.
"""

from __future__ import annotations

import argparse
import importlib
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from _machine import machine_info

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hktex_engine.config import KernelConfig, SpectralConfig  # noqa: E402
from hktex_engine.evaluation.synthetic import torus  # noqa: E402
from hktex_engine.geometry.operators import cotangent_stiffness, lumped_mass  # noqa: E402
from hktex_engine.geometry.sampling import sample_surface  # noqa: E402
from hktex_engine.kernels.hkt import hkt_bytes  # noqa: E402
from hktex_engine.kernels.knn import CandidateSearch  # noqa: E402
from hktex_engine.kernels.model import HeatKernelModel, KernelSet  # noqa: E402
from hktex_engine.kernels.query import AlbedoQuery  # noqa: E402
from hktex_engine.spectra.eigensolver import eigs_cold  # noqa: E402
from hktex_engine.spectra.grid import Spectra  # noqa: E402


def peak_rss_reset() -> None:
    """Reset the kernel's peak-RSS counter (VmHWM) of this process."""
    Path("/proc/self/clear_refs").write_text("5")


def rss_mb(field: str) -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def build_spectra(config: SpectralConfig, rng: np.random.Generator) -> Spectra:
    v, f = torus(128, 80)
    v = v - v.mean(axis=0)
    v = v * (2.0 / (v.max(axis=0) - v.min(axis=0)).max())
    mass = lumped_mass(v, f)
    iso_vals, iso_vecs = eigs_cold(cotangent_stiffness(v, f), mass, config.k_iso)
    n, g = v.shape[0], config.angles * len(config.anisotropies)
    scale = 1.0 / np.sqrt(mass.sum())  # M-normalised functions have this typical size
    evecs = (rng.standard_normal((n, g, config.k), dtype=np.float32) * scale).astype(np.float32)
    evals = np.sort(rng.uniform(0, 3000, (g, config.k)), axis=1)
    return Spectra(
        vertices=v,
        faces=f,
        mass=mass,
        grid_theta=np.linspace(0, np.pi, config.angles),
        grid_eta=np.asarray(config.anisotropies),
        evals=evals,
        evecs=evecs,
        iso_evals=np.maximum(iso_vals, 0),
        iso_evecs=iso_vecs,
        face_frames=np.tile([1.0, 0.0, 0.0], (f.shape[0], 1)),
        config=config,
        mesh_hash="benchmark-torus",
    )


def random_kernelset(spectra: Spectra, n: int, rng: np.random.Generator) -> KernelSet:
    face_ids, bary = sample_surface(spectra.vertices, spectra.faces, n, rng)
    return KernelSet(
        face_ids=face_ids,
        barycentrics=bary,
        theta=rng.uniform(0, np.pi, n),
        eta=1 + 99 * rng.uniform(size=n),
        threshold=rng.uniform(0.9, 1.0 - 1e-4, n),
        sharpness=10 + 40 * rng.uniform(size=n),
        colors=rng.uniform(-0.5, 0.5, (n, 3)),
        base_color=rng.uniform(0.2, 0.8, 3),
        kernel_config=KernelConfig(),
        mesh_hash=spectra.mesh_hash,
        config_hash=spectra.config_hash,
    )


def timed(fn, repeat: int = 1) -> tuple[float, object]:
    best, out = float("inf"), None
    for _ in range(repeat):
        start = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - start)
    return best, out


def bench_knn(query: AlbedoQuery, spectra: Spectra, n_q: int, k: int, rng) -> dict:
    centres = query.model._centre_emb
    f, b = sample_surface(spectra.vertices, spectra.faces, n_q, rng)
    q = query.field.embedding_at(torch.as_tensor(f), torch.as_tensor(b, dtype=torch.float32))
    out = {}
    results = {}
    for backend in ("faiss", "torch"):
        build_s, search = timed(lambda backend=backend: CandidateSearch(centres, backend))
        search_s, idx = timed(lambda search=search: search.search(q, k))
        out[backend] = {"build_s": round(build_s, 4), "search_s": round(search_s, 3)}
        results[backend] = idx
    same = (results["faiss"] == results["torch"]).float().mean().item()
    out["identical_fraction"] = round(same, 5)
    out["queries"], out["centres"], out["k"] = n_q, int(centres.shape[0]), k
    return out


def bench_pair_eval(query: AlbedoQuery, p: int, rng) -> dict:
    """The chosen batched-matmul pair evaluation against a direct (P, K_s, 4, K) gather."""
    model, field = query.model, query.field
    f, b = sample_surface(field.spectra.vertices, field.spectra.faces, p, rng)
    f, b = torch.as_tensor(f), torch.as_tensor(b, dtype=torch.float32)
    cand = model._knn.search(field.embedding_at(f, b), model.config.k_search)
    coef, _, nodes, weights, _ = model._terms

    def bmm_path():
        phi_y = field.node_values(f, b)
        dots = torch.bmm(coef[cand], phi_y.transpose(1, 2))
        return (dots.gather(2, nodes[cand]) * weights[cand]).sum(dim=2)

    def gather_path():
        phi_y = field.node_values(f, b)  # (P, G, K)
        rows = phi_y[torch.arange(p)[:, None, None], nodes[cand]]  # (P, K_s, 4, K)
        interp = (rows * weights[cand][..., None]).sum(dim=2)
        return (interp * coef[cand]).sum(dim=2)

    with torch.no_grad():
        t_bmm, h1 = timed(bmm_path, 3)
        t_gather, h2 = timed(gather_path, 3)
    err = float((h1 - h2).abs().max() / h1.abs().max())
    return {
        "points": p,
        "bmm_s": round(t_bmm, 4),
        "gather_s": round(t_gather, 4),
        "max_rel_diff": err,
    }


def bench_train_step(query: AlbedoQuery, ks: KernelSet, p: int, rng) -> dict:
    """One forward + backward with grad for all kernel parameters (what a fit step costs)."""
    model = HeatKernelModel.from_kernelset(ks, query.field)
    f, b = sample_surface(query.field.spectra.vertices, query.field.spectra.faces, p, rng)
    target = torch.rand(p, 3)

    def step():
        model.zero_grad()
        loss = ((model.albedo(f, b) - target) ** 2).mean()
        loss.backward()

    step()  # build the KNN index once
    t, _ = timed(step, 2)
    return {"points": p, "forward_backward_s": round(t, 3)}


def load_before(ref: str):
    """The evaluation modules as of git ``ref`` (interpolation, knn, kernels), importable side
    by side with the current ones, so before/after are timed in the same process and load."""
    tmp = Path(tempfile.mkdtemp(prefix="hktex_before_"))
    names = ("interpolation", "knn", "kernels")
    for name in names:
        src = subprocess.run(
            ["git", "show", f"{ref}:hktex_engine/{name}.py"],
            cwd=ROOT,
            capture_output=True,
            text=True,
            check=True,
        ).stdout
        for other in names:
            src = src.replace(f"from hktex_engine.{other} import", f"from _before_{other} import")
        (tmp / f"_before_{name}.py").write_text(src)
    sys.path.insert(0, str(tmp))
    return (
        importlib.import_module("_before_interpolation"),
        importlib.import_module("_before_kernels"),
    )


def _dense_colors(model, face_ids: np.ndarray, bary: np.ndarray, chunk: int) -> np.ndarray:
    """AlbedoQuery.colors' loop (sorted by face, chunked, no grad) for any model version."""
    order = np.argsort(face_ids, kind="stable")
    f, b = face_ids[order], bary[order]
    out = np.empty((f.shape[0], 3), dtype=np.float32)
    with torch.no_grad():
        for start in range(0, f.shape[0], chunk):
            sl = slice(start, start + chunk)
            fc, bc = torch.as_tensor(f[sl]), torch.as_tensor(b[sl], dtype=torch.float32)
            out[order[sl]] = model.albedo(fc, bc).numpy()
    return out


def bench_before_after(query: AlbedoQuery, ks: KernelSet, args, rng) -> dict:
    """Training step and query of the code at ``--before`` against the current code, timed
    alternately in the same run (the shared machine's load drifts; alternation spreads it)."""
    interp_old, kernels_old = load_before(args.before)
    spectra = query.field.spectra
    variants = {
        "before": kernels_old.HeatKernelModel.from_kernelset(
            ks, interp_old.SpectralField(spectra, device="cpu")
        ),
        "after": HeatKernelModel.from_kernelset(ks, query.field),
    }
    f, b = sample_surface(spectra.vertices, spectra.faces, 512, rng)
    target = torch.rand(512, 3)
    outs, grads = {}, {}

    def step(model, f, b, target, opt=None):
        model.zero_grad()
        out = model.albedo(f, b)
        ((out - target) ** 2).mean().backward()
        if opt is not None:
            opt.step()
            model.project_()
        return out

    for name, model in variants.items():  # warm up: KNN index, allocator
        outs[name] = step(model, f, b, target).detach()
        grads[name] = {n: p.grad.clone() for n, p in model.named_parameters()}
    # Timed steps as in a fit: a fresh batch each round and an Adam step (lr 1e-2 moves
    # some kernels into other grid cells, so caches keyed on cells see realistic churn).
    opts = {n: torch.optim.Adam(m.parameters(), lr=1e-2) for n, m in variants.items()}
    wall = {n: [] for n in variants}
    cpu = {n: [] for n in variants}
    regathered = []
    for _ in range(args.rounds):
        fr, br = sample_surface(spectra.vertices, spectra.faces, 512, rng)
        tr = torch.rand(512, 3)
        for name, model in variants.items():
            t0, c0 = time.perf_counter(), time.process_time()
            step(model, fr, br, tr, opts[name])
            wall[name].append(time.perf_counter() - t0)
            cpu[name].append(time.process_time() - c0)
        regathered.append(variants["after"]._rows.regathered)
    res: dict = {
        "train_step": {
            "points": 512,
            "rounds": args.rounds,
            "includes": "forward, backward, Adam step, projection",
            "centre_rows_regathered_per_step": regathered,
        }
    }
    for name in variants:
        res["train_step"][name] = {
            "min_s": round(min(wall[name]), 3),
            "median_s": round(statistics.median(wall[name]), 3),
            "median_cpu_s": round(statistics.median(cpu[name]), 3),
        }
    res["train_step"]["max_albedo_diff"] = float((outs["before"] - outs["after"]).abs().max())
    res["train_step"]["max_rel_grad_diff"] = {
        n: float(
            (grads["before"][n] - grads["after"][n]).abs().max()
            / grads["before"][n].abs().max().clamp(min=1e-30)
        )
        for n in grads["after"]
    }
    print("before/after train", json.dumps(res["train_step"]), flush=True)

    fq, bq = sample_surface(spectra.vertices, spectra.faces, args.compare_queries, rng)
    times = {n: [] for n in variants}
    colors = {}
    for _ in range(2):
        for name, model in variants.items():
            t0 = time.perf_counter()
            colors[name] = _dense_colors(model, fq, bq, query.chunk_points)
            times[name].append(time.perf_counter() - t0)
    diff = np.abs(colors["before"] - colors["after"]).max(axis=1)
    res["query"] = {
        "points": args.compare_queries,
        **{
            n: {"best_s": round(min(t), 2), "points_per_s": round(len(fq) / min(t))}
            for n, t in times.items()
        },
        "max_color_diff": float(diff.max()),
        "points_beyond_1e-4": int((diff > 1e-4).sum()),
    }
    print("before/after query", json.dumps(res["query"]), flush=True)
    res["ref"] = args.before
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--kernels", type=int, default=10_000)
    ap.add_argument("--queries", type=int, default=100_000)
    ap.add_argument("--million", type=int, default=1_000_000)
    ap.add_argument("--k", type=int, default=256)
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results")
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    ap.add_argument(
        "--only-million",
        action="store_true",
        help="skip to the million-point memory run; results go to kernels_million.json/.md",
    )
    ap.add_argument(
        "--time-budget",
        type=float,
        default=540.0,
        help="seconds for the whole run; the million-point run shrinks to fit (and says so)",
    )
    ap.add_argument(
        "--before",
        default="fc1d1ac",
        help="git ref whose interpolation/knn/kernels modules are timed against the current ones",
    )
    ap.add_argument("--rounds", type=int, default=5, help="alternating training-step rounds")
    ap.add_argument("--compare-queries", type=int, default=20_000)
    ap.add_argument("--skip-compare", action="store_true")
    args = ap.parse_args()
    started = time.perf_counter()
    if args.threads:
        torch.set_num_threads(args.threads)
    rng = np.random.default_rng(0)
    config = SpectralConfig(k=args.k)
    t0 = time.perf_counter()
    spectra = build_spectra(config, rng)
    ks = random_kernelset(spectra, args.kernels, rng)
    setup_s = time.perf_counter() - t0
    t_init, query = timed(lambda: AlbedoQuery(spectra, ks, device="cpu"))
    res: dict = {
        "command": "python " + " ".join(sys.argv),
        "machine": machine_info(device="cpu"),
        "setup": {
            "vertices": int(spectra.vertices.shape[0]),
            "faces": int(spectra.faces.shape[0]),
            "grid_nodes": int(spectra.evecs.shape[1]),
            "k": args.k,
            "k_iso": config.k_iso,
            "evecs_mb": round(spectra.evecs.nbytes / 2**20, 1),
            "kernels": args.kernels,
            "k_search": ks.kernel_config.k_search,
            "k_blend": ks.kernel_config.k_blend,
            "setup_s": round(setup_s, 2),
            "query_state_build_s": round(t_init, 3),
            "chunk_points": query.chunk_points,
            "bytes_per_point_estimate": query.bytes_per_point(),
        },
    }
    print(json.dumps(res["setup"]), flush=True)
    save(res, args.out)
    if args.only_million:
        return million_only(res, query, spectra, args, rng)
    if not args.skip_compare:
        res["before_after"] = bench_before_after(query, ks, args, rng)
        save(res, args.out)
    res["knn"] = bench_knn(query, spectra, args.queries, ks.kernel_config.k_search, rng)
    print("knn", json.dumps(res["knn"]), flush=True)
    save(res, args.out)
    res["pair_eval"] = bench_pair_eval(query, 1024, rng)
    print("pair_eval", json.dumps(res["pair_eval"]), flush=True)
    save(res, args.out)
    res["train_step"] = bench_train_step(query, ks, 512, rng)
    print("train_step", json.dumps(res["train_step"]), flush=True)
    save(res, args.out)

    f, b = sample_surface(spectra.vertices, spectra.faces, args.queries, rng)
    t_q, colors = timed(lambda: query.colors(f, b))
    res["query"] = {
        "points": args.queries,
        "seconds": round(t_q, 2),
        "points_per_s": round(args.queries / t_q),
    }
    print("query", json.dumps(res["query"]), flush=True)
    save(res, args.out)

    compact, full = hkt_bytes(ks), hkt_bytes(ks, compact=False)
    # (the colour effect of compact storage is measured on real spectra in tests/test_hkt.py;
    # random eigenvectors here would exaggerate it)
    res["hkt"] = {
        "compact_raw_bytes": compact["raw"],
        "compact_zip_bytes": compact["zip"],
        "float32_raw_bytes": full["raw"],
        "float32_zip_bytes": full["zip"],
    }
    print("hkt", json.dumps(res["hkt"]), flush=True)
    save(res, args.out)

    left = args.time_budget - (time.perf_counter() - started)
    n_million = int(min(args.million, max(0.0, 0.8 * left) * res["query"]["points_per_s"]))
    n_million = n_million // 1000 * 1000
    if n_million:
        fm, bm = sample_surface(spectra.vertices, spectra.faces, n_million, rng)
        base_mb = rss_mb("VmRSS")
        peak_rss_reset()
        t_m, _ = timed(lambda: query.colors(fm, bm))
        peak = rss_mb("VmHWM")
        res["million"] = {
            "points": n_million,
            "requested_points": args.million,
            "seconds": round(t_m, 1),
            "points_per_s": round(n_million / t_m),
            "rss_before_mb": round(base_mb, 1),
            "peak_rss_mb": round(peak, 1),
            "peak_above_before_mb": round(peak - base_mb, 1),
            "inputs_and_output_mb": round((fm.nbytes + bm.nbytes + n_million * 12) / 2**20, 1),
        }
        print("million", json.dumps(res["million"]), flush=True)
    res["total_s"] = round(time.perf_counter() - started, 1)
    save(res, args.out)


def million_only(res: dict, query: AlbedoQuery, spectra: Spectra, args, rng) -> None:
    """The whole requested point count, no time budget: peak memory is what this is for."""
    fm, bm = sample_surface(spectra.vertices, spectra.faces, args.million, rng)
    base_mb = rss_mb("VmRSS")
    peak_rss_reset()
    t_m, _ = timed(lambda: query.colors(fm, bm))
    peak = rss_mb("VmHWM")
    res["million"] = {
        "points": args.million,
        "seconds": round(t_m, 1),
        "points_per_s": round(args.million / t_m),
        "rss_before_mb": round(base_mb, 1),
        "peak_rss_mb": round(peak, 1),
        "peak_above_before_mb": round(peak - base_mb, 1),
        "inputs_and_output_mb": round((fm.nbytes + bm.nbytes + args.million * 12) / 2**20, 1),
    }
    print("million", json.dumps(res["million"]), flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "kernels_million.json").write_text(json.dumps(res, indent=1))
    m, s = res["million"], res["setup"]
    (args.out / "kernels_million.md").write_text(
        "# Kernel query memory for a million points (benchmarks/kernels.py --only-million)\n\n"
        f"Command: `{res['command']}`; machine as in kernels.md (load average at start "
        f"{res['machine']['load_average_1min']}, {res['machine']['torch_threads']} threads).\n"
        f"Grid {s['grid_nodes']} nodes x K = {s['k']}, {s['vertices']} vertices, {s['kernels']} "
        f"kernels, K_s = {s['k_search']}, chunk {s['chunk_points']} points.\n\n"
        f"{m['points']} points in {m['seconds']} s ({m['points_per_s']} points/s); process RSS "
        f"{m['rss_before_mb']} MB before (spectra arrays held twice: numpy and the device copy), "
        f"peak {m['peak_rss_mb']} MB, {m['peak_above_before_mb']} MB above the warm query state "
        f"(inputs + output {m['inputs_and_output_mb']} MB).\n"
    )


def save(res: dict, out: Path) -> None:
    """Written after every section, so a run cut short still leaves its numbers."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "kernels.json").write_text(json.dumps(res, indent=1))
    (out / "kernels.md").write_text(render_md(res))


def render_md(res: dict) -> str:
    if "hkt" not in res:
        return (
            "# Kernel evaluation benchmark (incomplete run)\n\n```\n"
            + json.dumps(res, indent=1)
            + "\n```\n"
        )
    s, k, q = res["setup"], res["knn"], res["query"]
    lines = [
        "# Kernel evaluation benchmark (benchmarks/kernels.py)",
        "",
        f"Command: `{res['command']}`  ",
        f"Machine: {res['machine']['platform']}, {res['machine']['cpus']} CPU cores "
        f"(shared with other jobs; load average at start {res['machine']['load_average_1min']}), "
        f"torch {res['machine']['torch']}, {res['machine']['torch_threads']} "
        "threads, CPU only.",
        "",
        f"Setup: torus, {s['vertices']} vertices; grid {s['grid_nodes']} nodes x K = {s['k']} "
        f"(random eigenvectors of the right shape, {s['evecs_mb']} MB float32; real K_iso = "
        f"{s['k_iso']} isotropic spectrum); {s['kernels']} kernels, K_s = {s['k_search']}, "
        f"K_c = {s['k_blend']}; chunk {s['chunk_points']} points.",
        "",
        "| measure | value |",
        "|---|---|",
        f"| query throughput ({q['points']} points) | {q['points_per_s']} points/s ({q['seconds']} s) |",
        f"| query state build (coefficients + KNN index) | {s['query_state_build_s']} s |",
        f"| KNN {k['centres']} centres x {k['queries']} queries, k = {k['k']}: faiss IndexFlatL2 | "
        f"{k['faiss']['search_s']} s (build {k['faiss']['build_s']} s) |",
        f"| same, torch addmm + topk (chunked) | {k['torch']['search_s']} s (build {k['torch']['build_s']} s) |",
        f"| faiss and torch neighbour lists identical | {k['identical_fraction'] * 100:.3f} % of entries |",
        f"| pair evaluation, {res['pair_eval']['points']} points: batched matmul | {res['pair_eval']['bmm_s']} s |",
        f"| same, direct (P, K_s, 4, K) gather | {res['pair_eval']['gather_s']} s |",
        f"| one training forward+backward, {res['train_step']['points']} points | "
        f"{res['train_step']['forward_backward_s']} s |",
        f"| .hkt compact: raw / zip bytes | {res['hkt']['compact_raw_bytes']} / {res['hkt']['compact_zip_bytes']} |",
        f"| .hkt float32: raw / zip bytes | {res['hkt']['float32_raw_bytes']} / {res['hkt']['float32_zip_bytes']} |",
    ]
    if "million" in res:
        m = res["million"]
        if m["points"] < m["requested_points"]:
            lines.append(
                f"| (million run shrunk to {m['points']} points to fit the time budget on the shared CPU) | |"
            )
        lines += [
            f"| {m['points']} points: time | {m['seconds']} s ({m['points_per_s']} points/s) |",
            f"| {m['points']} points: peak RSS / above the warm query state | "
            f"{m['peak_rss_mb']} MB / {m['peak_above_before_mb']} MB (inputs + output "
            f"{m['inputs_and_output_mb']} MB) |",
        ]
    if "before_after" in res:
        ba = res["before_after"]
        tr, qu = ba["train_step"], ba["query"]
        lines += [
            "",
            f"Before (`{ba['ref']}`) / after (this commit), same process, timed alternately "
            f"({tr['rounds']} training rounds, 2 query rounds):",
            "",
            "| measure | before | after |",
            "|---|---|---|",
            f"| training step (forward, backward, Adam, projection), {tr['points']} points, min / median wall s | "
            f"{tr['before']['min_s']} / {tr['before']['median_s']} | "
            f"{tr['after']['min_s']} / {tr['after']['median_s']} |",
            f"| same, median CPU s | {tr['before']['median_cpu_s']} | {tr['after']['median_cpu_s']} |",
            f"| query {qu['points']} points (AlbedoQuery loop), points/s | "
            f"{qu['before']['points_per_s']} | {qu['after']['points_per_s']} |",
            "",
            f"Training albedo max difference {tr['max_albedo_diff']:.2e}; largest relative gradient "
            f"difference {max(tr['max_rel_grad_diff'].values()):.2e} "
            f"({max(tr['max_rel_grad_diff'], key=tr['max_rel_grad_diff'].get)}); query colours max "
            f"difference {qu['max_color_diff']:.2e}, {qu['points_beyond_1e-4']} points beyond 1e-4.",
        ]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
