"""Benchmark of the FE plant: the default 4 x 10 mm layer (1000 steps, IN625) vs the
textbook scikit-fem approach on the same mesh.

Usage: ``python benchmarks/bench_fe.py [--h-um 25] [--baseline-steps 5]
[--baseline-mem-gb 16] [--baseline-timeout-s 600]``.  Last line of stdout is JSON.

Baseline (as scikit-fem's heat-equation example): assemble ``K`` and ``M`` with
``Basis(mesh, ElementHex1(), intorder=2)``, factorise ``A = M + dt alpha K`` once with
``scipy.sparse.linalg.splu``, then one back-substitution per step (implicit Euler,
constant properties - i.e. less physics than the benchmarked model).  It runs in a
child process with an address-space limit and a timeout so it cannot take the machine
down; if it fails, its fields are null and the reason is reported.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))


def baseline(h_um: float, n_steps: int) -> dict:
    import numpy as np
    from scipy.sparse.linalg import splu
    from skfem import Basis, BilinearForm, ElementHex1
    from skfem.helpers import dot, grad

    from fe_node.scenarios import scenario
    from fe_node.solver import build_grid

    sc = scenario("layer", h_fine_m=h_um * 1e-6)
    mesh, _ = build_grid(sc.settings, sc.plan).skfem_mesh()
    t0 = time.perf_counter()
    basis = Basis(mesh, ElementHex1(), intorder=2)

    @BilinearForm
    def laplace(u, v, w):
        return dot(grad(u), grad(v))

    @BilinearForm
    def mass(u, v, w):
        return u * v

    K, M = laplace.assemble(basis), mass.assemble(basis)
    t1 = time.perf_counter()
    mat = sc.settings.material
    alpha = mat.k(300.0) / (mat.rho * mat.cp(300.0))
    lu = splu((M + sc.settings.dt_s * alpha * K).T.tocsc())
    t2 = time.perf_counter()
    u = np.full(mesh.p.shape[1], 300.0)
    f = np.zeros_like(u)
    f[np.argmin(np.sum(mesh.p**2, axis=0))] = 1e-9
    t3 = time.perf_counter()
    for _ in range(n_steps):
        u = lu.solve(M @ u + f)
    t4 = time.perf_counter()
    return dict(baseline_assemble_s=t1 - t0, baseline_factor_s=t2 - t1,
                baseline_ms_per_step=(t4 - t3) / n_steps * 1e3,
                baseline_peak_rss_gb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6)


def run_baseline(h_um: float, n_steps: int, mem_gb: float, timeout_s: float) -> dict:
    def limit():
        lim = int(mem_gb * 2**30)
        resource.setrlimit(resource.RLIMIT_AS, (lim, lim))

    cmd = [sys.executable, os.path.abspath(__file__), "--child-baseline",
           "--h-um", str(h_um), "--baseline-steps", str(n_steps)]
    try:
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s, preexec_fn=limit)
    except subprocess.TimeoutExpired:
        return dict(baseline_ms_per_step=None, baseline_error=f"timeout after {timeout_s} s")
    if p.returncode != 0:
        tail = (p.stderr.strip().splitlines() or ["?"])[-1]
        return dict(baseline_ms_per_step=None,
                    baseline_error=f"failed (limit {mem_gb} GB address space): {tail}")
    return json.loads(p.stdout.strip().splitlines()[-1])


def layer(h_um: float) -> dict:
    from fe_node.scenarios import scenario
    from fe_node.solver import ThermalModel

    t0 = time.perf_counter()
    sc = scenario("layer", h_fine_m=h_um * 1e-6)
    model = ThermalModel(sc.settings, sc.plan)
    t1 = time.perf_counter()
    n = 0
    while not model.done:
        obs = model.step(*sc.profile.command(model.step_index))
        n += 1
    t2 = time.perf_counter()
    return dict(layer_wall_s=t2 - t0, setup_s=t1 - t0, ms_per_step=(t2 - t1) / n * 1e3,
                steps=n, substeps_per_step=model.n_substeps, h_um=h_um,
                nodes=model.grid.n_nodes, energy_error_pct=obs.energy_error_pct,
                final_area_mm2=obs.area_m2 * 1e6)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--h-um", type=float, default=25.0)
    ap.add_argument("--baseline-steps", type=int, default=5)
    ap.add_argument("--baseline-mem-gb", type=float, default=16.0,
                    help="address-space limit of the splu baseline (it needs ~11 GB at 25 µm)")
    ap.add_argument("--baseline-timeout-s", type=float, default=600.0)
    ap.add_argument("--child-baseline", action="store_true", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.child_baseline:
        print(json.dumps(baseline(a.h_um, a.baseline_steps)))
        return
    res = layer(a.h_um)
    print(f"layer: {res}", file=sys.stderr)
    res.update(run_baseline(a.h_um, a.baseline_steps, a.baseline_mem_gb, a.baseline_timeout_s))
    b = res.get("baseline_ms_per_step")
    res["speedup_vs_baseline"] = b / res["ms_per_step"] if b else None
    print(json.dumps(res))


if __name__ == "__main__":
    main()
