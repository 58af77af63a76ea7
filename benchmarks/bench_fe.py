"""Benchmark of the FE plant: the default 4 x 10 mm layer (1000 steps, IN625) on the uniform mesh
vs the textbook scikit-fem approach on the same mesh.

Usage: ``python benchmarks/bench_fe.py [--preset physical] [--h-um 25] [--compare-steps 100]
[--baseline-steps 5] [--baseline-mem-gb 16] [--baseline-timeout-s 600]``.  Last line of stdout is
JSON.  ``--preset`` (:mod:`fe_node.presets`, default the default plant's) sets the plant.

Same scheme, two operators: the first ``--compare-steps`` steps of the layer are run with the
explicit enthalpy scheme on the tensor-product operator (``fast_ms_per_step``) and on the
scikit-fem-assembled CSR operator (``csr_ms_per_step``, ``Settings.operator = "csr"``), one
step of each in turn so both see the same machine load (medians; ``load_avg`` before/after).
``explicit_csr_speedup`` = csr / fast: what the tensor path gains over the same explicit
scheme with a CSR matrix.  ``speedup_vs_baseline`` compares with implicit ``splu`` stepping.

Baseline (as scikit-fem's heat-equation example): assemble ``K`` and ``M`` with
``Basis(mesh, ElementHex1(), intorder=2)``, factorise ``A = M + dt alpha K`` once with
``scipy.sparse.linalg.splu``, then one back-substitution per step (implicit Euler,
constant properties - i.e. less physics than the benchmarked model).  It runs in a
child process with an address-space limit and a timeout so it cannot take the machine
down; if it fails, its fields are null and the reason is reported.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import resource
import subprocess
import sys
import time

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))


def baseline(preset: str, h_um: float, n_steps: int) -> dict:
    import numpy as np
    from scipy.sparse.linalg import splu
    from skfem import Basis, BilinearForm, ElementHex1
    from skfem.helpers import dot, grad

    from fe_node.scenarios import scenario
    from fe_node.solver import build_grid

    sc = scenario("layer", preset=preset, h_fine_m=h_um * 1e-6, mesh="uniform")
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


def run_baseline(preset: str, h_um: float, n_steps: int, mem_gb: float, timeout_s: float) -> dict:
    def limit():
        lim = int(mem_gb * 2**30)
        resource.setrlimit(resource.RLIMIT_AS, (lim, lim))

    cmd = [sys.executable, os.path.abspath(__file__), "--child-baseline", "--preset", preset,
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


def layer(preset: str, h_um: float) -> dict:
    from fe_node.scenarios import scenario
    from fe_node.solver import ThermalModel

    t0 = time.perf_counter()
    sc = scenario("layer", preset=preset, h_fine_m=h_um * 1e-6, mesh="uniform")
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


def compare_operators(preset: str, h_um: float, n_steps: int) -> dict:
    """Per-step wall time of the same explicit scheme with either operator (module docstring)."""
    import numpy as np

    from fe_node.scenarios import scenario
    from fe_node.solver import ThermalModel

    sc = scenario("layer", preset=preset, h_fine_m=h_um * 1e-6, mesh="uniform")
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    csr = ThermalModel(dataclasses.replace(sc.settings, operator="csr"), sc.plan)
    csr_setup = time.perf_counter() - t0
    fast = ThermalModel(sc.settings, sc.plan)
    times, area = {"fast": [], "csr": []}, {}
    for _ in range(n_steps):
        cmd = sc.profile.command(fast.step_index)
        for name, model in (("fast", fast), ("csr", csr)):
            t = time.perf_counter()
            area[name] = model.step(*cmd).area_m2
            times[name].append(time.perf_counter() - t)
    fast_ms, csr_ms = (float(np.median(times[k])) * 1e3 for k in ("fast", "csr"))
    return dict(fast_ms_per_step=fast_ms, csr_ms_per_step=csr_ms, explicit_csr_speedup=csr_ms / fast_ms,
                compare_steps=n_steps, csr_setup_s=csr_setup, csr_nnz=int(csr.operator.matrix.nnz),
                compare_area_rel_diff=abs(area["csr"] - area["fast"]) / area["fast"],
                load_avg=[load0, os.getloadavg()[0]])


def main() -> None:
    from fe_node.presets import DEFAULT, NAMES

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", choices=NAMES, default=DEFAULT, help="plant preset (default %(default)s)")
    ap.add_argument("--h-um", type=float, default=25.0)
    ap.add_argument("--compare-steps", type=int, default=100)
    ap.add_argument("--baseline-steps", type=int, default=5)
    ap.add_argument("--baseline-mem-gb", type=float, default=16.0,
                    help="address-space limit of the splu baseline (it needs ~11 GB at 25 µm)")
    ap.add_argument("--baseline-timeout-s", type=float, default=600.0)
    ap.add_argument("--child-baseline", action="store_true", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.child_baseline:
        print(json.dumps(baseline(a.preset, a.h_um, a.baseline_steps)))
        return
    res = layer(a.preset, a.h_um)
    print(f"layer: {res}", file=sys.stderr)
    res.update(compare_operators(a.preset, a.h_um, a.compare_steps))
    print(f"operators: {res}", file=sys.stderr)
    res.update(run_baseline(a.preset, a.h_um, a.baseline_steps, a.baseline_mem_gb, a.baseline_timeout_s))
    b = res.get("baseline_ms_per_step")
    res["speedup_vs_baseline"] = b / res["ms_per_step"] if b else None
    print(json.dumps(res))


if __name__ == "__main__":
    main()
