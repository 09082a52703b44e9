"""The JAX engine composed (issue 27): inside the caller's jit, under grad and vmap, the IMM under
grad, and the parallel-in-time filter against T; beside dynamax, in one process on the same data.

Run ``python benchmarks/compose.py [--quick]`` (after ``make benchmark`` has installed the rivals of
benchmarks/requirements.txt). Every row is timed ``REPEATS`` times after a first (compiling) call,
the repeats of the rows compared with each other interleaved round robin (a burst of load from other
jobs hits them alike); reported: the median rate and the min-max range over the repeats, the ratio of
the medians, and the agreement of the results. The process is pinned to one core, as
``benchmarks/filters.py``. Writes ``benchmarks/compose.json`` and ``book/performance_compose.md``
(included by ``book/performance.md``); ``--quick`` prints only; ``--only grad,imm`` re-measures those
sections alone and keeps the others from compose.json (the page says which, when, under what load).
The ``memory`` section reports XLA's compiled memory analysis of ``jit(grad)`` of the total
log-likelihood at long T, without and with ``total_loglik(..., checkpoint=c)`` (``jax.checkpoint``
over segments of c steps), and the gradient's time both ways.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if hasattr(os, "sched_setaffinity"):
    os.sched_setaffinity(0, {0})

import numpy as np  # noqa: E402

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402

from kftrack import imm, tuning  # noqa: E402
from kftrack.kalman import kalman_filter  # noqa: E402
from kftrack.models import ConstantVelocity, KnownTurn  # noqa: E402
from kftrack.parallel import parallel_filter  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from filters import DT, Q_DENSITY, SIGMA_Z, TURN_RATE, cv_model, fmt_rate, md_table, simulate  # noqa: E402

EPS = np.finfo(float).eps
C_BOUND = 10.0


def block(t):
    return jax.block_until_ready(t)


def measure(fns: dict, work: dict, repeats: int) -> dict:
    """``{key: {median, min, max (steps/s), compile_s, out}}``: each ``fns[key]()`` called once
    (compiles; its time beyond the median is the compile time), then ``repeats`` times, round robin."""
    out, times = {}, {k: [] for k in fns}
    for k, fn in fns.items():
        t0 = time.perf_counter()
        res = block(fn())
        out[k] = {"first_s": time.perf_counter() - t0, "out": res}
    for _ in range(repeats):
        for k, fn in fns.items():
            t0 = time.perf_counter()
            block(fn())
            times[k].append(time.perf_counter() - t0)
    for k, ts in times.items():
        rates = work[k] / np.array(ts)
        med_t = float(np.median(ts))
        out[k].update(median=float(np.median(rates)), min=float(rates.min()), max=float(rates.max()),
                      compile_s=max(0.0, out[k]["first_s"] - med_t), repeats=len(ts))
    return out


def dynamax_params(x0, P0, F, Q, H, R):
    from dynamax.linear_gaussian_ssm.inference import (ParamsLGSSM, ParamsLGSSMDynamics, ParamsLGSSMEmissions,
                                                       ParamsLGSSMInitial)
    n, m = F.shape[-1], H.shape[-2]
    return ParamsLGSSM(
        initial=ParamsLGSSMInitial(mean=jnp.asarray(x0), cov=jnp.asarray(P0)),
        dynamics=ParamsLGSSMDynamics(weights=jnp.asarray(F), bias=jnp.zeros(n), input_weights=jnp.zeros((n, 0)),
                                     cov=jnp.asarray(Q)),
        emissions=ParamsLGSSMEmissions(weights=jnp.asarray(H), bias=jnp.zeros(m), input_weights=jnp.zeros((m, 0)),
                                       cov=jnp.asarray(R)))


def rel(a, b) -> float:
    """max |a - b| / max |b| over every entry (of pytrees alike)."""
    la, lb = jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)
    return max(float(np.max(np.abs(np.asarray(u) - np.asarray(v))) / np.max(np.abs(np.asarray(v))))
               for u, v in zip(la, lb))


def kappa_cv(F, Q, H, R, P0, T):
    """max cond(P^-), cond(S) of the shared covariance recursion (one track)."""
    P, worst = P0, 0.0
    for _ in range(T):
        S = H @ P @ H.T + R
        worst = max(worst, np.linalg.cond(P), np.linalg.cond(S))
        K = np.linalg.solve(S, H @ P).T
        P = F @ ((np.eye(4) - K @ H) @ P) @ F.T + Q
    return float(worst)


OUT_JSON, OUT_MD = ROOT / "benchmarks" / "compose.json", ROOT / "book" / "performance_compose.md"
SECTIONS = ("jit", "grad", "vmap", "imm", "parallel", "memory")


def memory_of(compiled) -> dict:
    """XLA's buffer assignment of a compiled program (bytes): temporaries, arguments, outputs; None
    where the backend reports none. Deterministic for a program and backend: not a measurement."""
    ma = compiled.memory_analysis()
    if ma is None:
        return None
    return {"temp": int(ma.temp_size_in_bytes), "argument": int(ma.argument_size_in_bytes),
            "output": int(ma.output_size_in_bytes)}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--render-only", action="store_true", help="re-write the page fragment from compose.json")
    ap.add_argument("--only", default="", help="comma-separated sections to re-measure (jit, grad, vmap, imm, "
                    "parallel, memory), the others kept from compose.json; the page notes the date and load of each")
    opts = ap.parse_args(argv)
    if opts.render_only:
        res = json.loads(OUT_JSON.read_text())
        OUT_MD.write_text(render(res))
        return res
    q = opts.quick
    only = [w for w in opts.only.split(",") if w]
    if set(only) - set(SECTIONS):
        ap.error(f"--only takes {', '.join(SECTIONS)}; got {opts.only!r}")
    want = lambda section: not only or section in only  # noqa: E731

    def save(res):  # after each section: a run cut short keeps what it measured
        if only:  # the load at the end of the full run stays the full run's
            res["load_average_at_end"] = full_end
        if not q:
            OUT_JSON.write_text(json.dumps(res, indent=1) + "\n")
    RUNS, T = (100, 100) if q else (1000, 500)
    REPEATS = 3 if q else 5
    t_start = time.perf_counter()
    load0 = os.getloadavg()[0]
    F, Q, H, R = cv_model()
    Qbar = Q / Q_DENSITY
    x0, P0 = np.zeros(4), 100.0 * np.eye(4)
    zs = simulate(np.random.default_rng(2026), RUNS, T, [F], [Q])
    zj = jax.device_put(jnp.asarray(zs))
    yj = jax.device_put(jnp.asarray(zs.transpose(1, 0, 2)))  # dynamax: (runs, T, m)
    from dynamax.linear_gaussian_ssm.inference import lgssm_filter as dyn_filter
    from dynamax.linear_gaussian_ssm.parallel_inference import lgssm_filter as dyn_parallel
    params = dynamax_params(x0, P0, F, Q, H, R)
    kap = kappa_cv(F, Q, H, R, P0, T)
    bound = C_BOUND * T * 4 * kap * EPS
    boost = T * 1e-9 / float(np.linalg.eigvalsh(R)[0])  # dynamax's diagonal_boost, as benchmarks/filters.py
    res = {"date": datetime.date.today().isoformat(), "runs": RUNS, "steps": T, "repeats": REPEATS,
           "load_average_at_start": load0, "kappa": kap, "bound": bound, "dynamax_boost_bound": boost}
    if only:  # the other sections as measured before; these re-measured, with their own date and load
        res = json.loads(OUT_JSON.read_text())
        full_end = res["load_average_at_end"]
        res["remeasured"] = {k: v for k, v in res.get("remeasured", {}).items() if k not in only}
    kf = lambda z, **kw: kalman_filter(z, x0, P0, F, Q, H, R, missing=False, **kw)  # noqa: E731
    print(f"{RUNS} runs x {T} steps, 2-D CV; {REPEATS} interleaved repeats; load {load0:.1f}", flush=True)

    def stamp(section):  # a re-measured section: its date and the load around it
        if only:
            res["remeasured"][section] = {"date": datetime.date.today().isoformat(), "load_start": stamp.load,
                                          "load_end": os.getloadavg()[0]}
        stamp.load = os.getloadavg()[0]
    stamp.load = load0

    def done(section, value, m, keys):  # the end of a section: store it, stamp it, save, report
        res[section] = value
        res["load_average_at_end"] = os.getloadavg()[0]
        stamp(section)
        save(res)
        print(json.dumps({k: {kk: v.get(kk) for kk in keys} for k, v in m.items()}), flush=True)

    # ---- inside the caller's jit ---------------------------------------------------------------
    if want("jit"):
        jx_means = jax.jit(lambda z: kf(z).x)
        jx_full = jax.jit(lambda z: (lambda r: (r.x, r.P, r.loglik))(kf(z, priors=False)))
        dm_means = jax.jit(jax.vmap(lambda y: dyn_filter(params, y).filtered_means))
        dm_full = jax.jit(jax.vmap(lambda y: (lambda p: (p.filtered_means, p.filtered_covariances, p.marginal_loglik))(
            dyn_filter(params, y))))
        fns = {"direct_post": lambda: kf(zj, priors=False).x, "jit_means": lambda: jx_means(zj),
               "jit_full": lambda: jx_full(zj), "dyn_means": lambda: dm_means(yj), "dyn_full": lambda: dm_full(yj)}
        m = measure(fns, dict.fromkeys(fns, RUNS * T), REPEATS)
        ref = np.asarray(m["direct_post"]["out"])
        for k in fns:
            x = m[k]["out"][0] if isinstance(m[k]["out"], tuple) else m[k]["out"]
            x = np.swapaxes(np.asarray(x), 0, 1) if k.startswith("dyn") else np.asarray(x)
            m[k]["rel_diff"] = rel(x, ref)
            m[k].pop("out")
        done("jit", m, m, ("median", "min", "max", "rel_diff"))

    # ---- grad of the total log-likelihood wrt (log q, log r) ----------------------------------
    if want("grad"):
        def kf_ll(phi):  # the sum alone: kftrack.engines.run_total_scan, no stored sequence
            return tuning.total_loglik(phi, lambda p: (F, p[0] * Qbar, H, p[1] * R / SIGMA_Z**2), zj, x0, P0,
                                       missing=False)

        def dm_ll(phi):
            p = dynamax_params(x0, P0, F, jnp.exp(phi[0]) * Qbar, H, jnp.exp(phi[1]) * R / SIGMA_Z**2)
            return jnp.sum(jax.vmap(lambda y: dyn_filter(p, y).marginal_loglik)(yj))

        phi = jnp.asarray([np.log(Q_DENSITY * 1.5), np.log(SIGMA_Z**2 * 0.8)])
        g_kf, g_dm = jax.jit(jax.grad(kf_ll)), jax.jit(jax.grad(dm_ll))
        f_kf, f_dm = jax.jit(kf_ll), jax.jit(dm_ll)
        fns = {"kf_grad": lambda: g_kf(phi), "dyn_grad": lambda: g_dm(phi), "kf_loglik": lambda: f_kf(phi),
               "dyn_loglik": lambda: f_dm(phi)}
        m = measure(fns, dict.fromkeys(fns, RUNS * T), REPEATS)
        m["dyn_grad"]["rel_diff"] = rel(m["dyn_grad"]["out"], m["kf_grad"]["out"])
        m["dyn_loglik"]["rel_diff"] = rel(m["dyn_loglik"]["out"], m["kf_loglik"]["out"])
        res["grad_value"] = [float(v) for v in np.asarray(m["kf_grad"]["out"])]
        for k in fns:
            m[k].pop("out")
        done("grad", m, m, ("median", "min", "max", "rel_diff"))

    # ---- vmap over 64 values of q against 64 direct calls --------------------------------------
    if want("vmap"):
        RV, TV, NQ = (20, 50, 8) if q else (100, 200, 64)
        zv = jnp.asarray(zs[:TV, :RV])
        qs = np.geomspace(0.01, 1.0, NQ)
        vm = jax.jit(jax.vmap(lambda qq: kalman_filter(zv, x0, P0, F, qq * Qbar, H, R, missing=False, priors=False).x))
        qj = jnp.asarray(qs)

        def direct():
            return jnp.stack([kalman_filter(zv, x0, P0, F, qq * Qbar, H, R, missing=False, priors=False).x
                              for qq in qs])
        fns = {"vmap_q": lambda: vm(qj), "direct_q": direct}
        m = measure(fns, dict.fromkeys(fns, NQ * RV * TV), REPEATS)
        m["vmap_q"]["rel_diff"] = rel(m["vmap_q"]["out"], m["direct_q"]["out"])
        kq = max(kappa_cv(F, qq * Qbar, H, R, P0, TV) for qq in qs)
        m["vmap_q"]["bound"] = C_BOUND * TV * 4 * kq * EPS
        for k in fns:
            m[k].pop("out")
        done("vmap", {"runs": RV, "steps": TV, "n_q": NQ, **m}, m, ("median", "min", "max", "rel_diff"))

    # ---- the IMM under grad against its forward pass ------------------------------------------
    if want("imm"):
        RI, TI = (20, 50) if q else (100, 200)
        models = [ConstantVelocity(ndim=2, q=Q_DENSITY), KnownTurn(omega=TURN_RATE, ndim=2, q=Q_DENSITY),
                  KnownTurn(omega=-TURN_RATE, ndim=2, q=Q_DENSITY)]
        Fm, Qm = np.stack([mm.F(DT) for mm in models]), np.stack([mm.Q(DT) for mm in models])
        Pi = np.full((3, 3), 0.025) + 0.925 * np.eye(3)
        zi = jnp.asarray(simulate(np.random.default_rng(2027), RI, TI, list(Fm), list(Qm), Pi))
        Rm = SIGMA_Z**2 * np.eye(2)

        def imm_ll(th):
            p = imm.IMMParams(Fm, jnp.exp(th[:3])[:, None, None] * Qm / Q_DENSITY, H, Rm, jnp.reshape(th[3:], (3, 3)),
                              np.log(np.full(3, 1 / 3)))
            return jnp.sum(imm.imm_loglik(p, zi, np.array([0.0, 10.0, 0.0, 0.0]), P0, missing=False, sequence=False)[0])

        th = jnp.asarray(np.concatenate([np.log(np.full(3, Q_DENSITY)), np.log(Pi).ravel()]))
        fi, gi = jax.jit(imm_ll), jax.jit(jax.grad(imm_ll))
        fns = {"imm_forward": lambda: fi(th), "imm_grad": lambda: gi(th)}
        m = measure(fns, dict.fromkeys(fns, RI * TI), REPEATS)
        for k in fns:
            m[k].pop("out")
        done("imm", {"runs": RI, "steps": TI, **m}, m, ("median", "min", "max", "compile_s"))

    # ---- parallel in time against T, one run -------------------------------------------------
    if want("parallel"):
        Ts = (100, 1000) if q else (100, 1000, 10_000)
        par = {}
        for TT in Ts:
            z1 = simulate(np.random.default_rng(TT), 1, TT, [F], [Q])[:, 0]
            z1j = jnp.asarray(z1)
            seq_j = jax.jit(lambda z: kalman_filter(z, x0, P0, F, Q, H, R, missing=False, priors=False).x)
            par_j = jax.jit(lambda z: parallel_filter(z, x0, P0, F, Q, H, R, missing=False).x)
            dseq = jax.jit(lambda z: dyn_filter(params, z).filtered_means)
            dpar = jax.jit(lambda z: dyn_parallel(params, z).filtered_means)
            fns = {"kf_sequential": lambda: seq_j(z1j), "kf_parallel": lambda: par_j(z1j),
                   "dyn_sequential": lambda: dseq(z1j), "dyn_parallel": lambda: dpar(z1j)}
            m = measure(fns, dict.fromkeys(fns, TT), REPEATS)
            ref = np.asarray(kalman_filter(z1, x0, P0, F, Q, H, R).x)
            for k in fns:
                m[k]["rel_diff"] = rel(m[k].pop("out"), ref)
            m["bound"] = C_BOUND * TT * 4 * kappa_cv(F, Q, H, R, P0, min(TT, 1000)) * EPS
            par[str(TT)] = m
            res["load_average_at_end"] = os.getloadavg()[0]
            res["parallel"] = par
            save(res)
            print(TT, json.dumps({k: {kk: v.get(kk) for kk in ("median", "min", "max", "rel_diff", "compile_s")}
                                  for k, v in m.items() if k != "bound"}), flush=True)
        res["parallel"] = par
        stamp("parallel")

    # ---- memory of the gradient at long T: total_loglik(..., checkpoint=c) ----------------------
    if want("memory"):
        RM = 100
        Ts = (1000, 10_000) if q else (1000, 10_000, 100_000)
        phi = jnp.asarray([np.log(Q_DENSITY * 1.5), np.log(SIGMA_Z**2 * 0.8)])
        build = lambda p: (F, p[0] * Qbar, H, p[1] * R / SIGMA_Z**2)  # noqa: E731  as the grad section
        mem = {"runs": RM, "repeats": min(REPEATS, 3), "jax": jax.__version__}
        for TT in Ts:
            c = round(TT ** 0.5)
            zm = jnp.asarray(simulate(np.random.default_rng(TT + 1), RM, TT, [F], [Q]))

            def ll(p, z, ck=None):
                return tuning.total_loglik(p, build, z, x0, P0, missing=False, checkpoint=ck)
            progs, comp = {}, {}
            for k, fn in (("forward", ll), ("grad", jax.grad(ll)), ("grad_ckpt", jax.grad(lambda p, z: ll(p, z, c)))):
                t0 = time.perf_counter()
                progs[k] = jax.jit(fn).lower(phi, zm).compile()
                comp[k] = time.perf_counter() - t0
            fns = {k: (lambda k=k: progs[k](phi, zm)) for k in ("grad", "grad_ckpt")}
            m = measure(fns, dict.fromkeys(fns, RM * TT), min(REPEATS, 3))  # 3: a call at T = 1e5 takes seconds
            m["grad_ckpt"]["rel_diff"] = rel(m["grad_ckpt"]["out"], m["grad"]["out"])
            for k in fns:
                m[k].pop("out")
                m[k]["compile_s"] = comp[k]
            mem[str(TT)] = {"c": c, "bytes": {k: memory_of(pr) for k, pr in progs.items()}, **m}
            res["memory"] = mem
            res["load_average_at_end"] = os.getloadavg()[0]
            save(res)
            print(TT, c, json.dumps(mem[str(TT)]["bytes"]), json.dumps(
                {k: {kk: m[k].get(kk) for kk in ("median", "min", "max", "rel_diff", "compile_s")} for k in fns}),
                flush=True)
        res["memory"] = mem
        stamp("memory")
    res["load_average_at_end"] = os.getloadavg()[0]
    if not only:
        res["total_s"] = time.perf_counter() - t_start
    if not q:
        save(res)  # (restores the full run's end load under --only)
        OUT_MD.write_text(render(res))
        print("wrote benchmarks/compose.json, book/performance_compose.md")
    return res


def render(res) -> str:
    def cell(r):
        return f"{fmt_rate(r['median'])} ({fmt_rate(r['min'])}–{fmt_rate(r['max'])})"

    def ratio(a, b, need=None):
        v = a["median"] / b["median"]
        lo, hi = a["min"] / b["max"], a["max"] / b["min"]
        s = f"{v:.2f}× ({lo:.2f}–{hi:.2f})"
        if need is not None:
            s += " — " + ("met" if lo >= need else ("missed" if hi < need else "not resolved by the spread"))
        return s

    def diff(r, bound=None):
        d = r.get("rel_diff")
        if d is None:
            return ""
        s = "0 (bitwise)" if d == 0 else f"below 1e{int(np.ceil(np.log10(d)))}"
        return s + (f" (bound {bound:.1g})" if bound else "")

    j, g, v, im, p, mm = (res.get(k) for k in SECTIONS)
    b = res["bound"]
    bb = b + res["dynamax_boost_bound"]
    L = ["<!-- generated by benchmarks/compose.py: do not edit by hand -->", ""]
    every = set(res.get("remeasured", {})) >= {k for k in SECTIONS if res.get(k)}
    load = ("each section has since been re-measured alone, its 1-minute load average on 2 cores noted below; "
            "absolute rates vary with the load" if every else
            f"1-minute load average {res['load_average_at_start']:.1f} at the start, "
            f"{res['load_average_at_end']:.1f} at the end, on 2 cores: absolute rates are depressed and noisy")
    L.append(f"Measured on {res['date']}, the process pinned to one core of the two-core machine of the tables "
             f"above, which other engineers were using at the same time ({load}). Each row: the median of {res['repeats']} repeats after "
             "a compiling call, with the min–max range; the repeats of the rows compared are interleaved. A ratio is "
             "of the medians, with the range from the extremes (min/max to max/min); \"met\" only when the whole "
             "range is at or above the target, \"missed\" when the whole range is below it, \"not resolved by the "
             "spread\" otherwise. The target of every ratio so marked is 1: kftrack at least as fast as the call it "
             "is compared with.")
    names = {"jit": "composed calls", "grad": "grad", "vmap": "vmap over q", "imm": "IMM under grad",
             "parallel": "parallel in time", "memory": "memory at long T"}
    for sec, st in res.get("remeasured", {}).items():
        L.append("")
        L.append(f"The {names[sec]} rows were re-measured on {st['date']}, alone (`--only {sec}`), under load "
                 f"{st['load_start']:.1f} at the start and {st['load_end']:.1f} at the end of that section.")
    L.append("")
    if j and g:
        L.append(f"**Composed calls**, {res['runs']} runs × {res['steps']} steps (2-D constant velocity, float64, "
                 "`missing=False`: the shared-covariance path inside the trace), filter-steps/s:")
        L.append("")
        rows = [
            ["kftrack `kalman_filter(..., priors=False).x`, direct call (JAX arrays)", cell(j["direct_post"]), "",
             "the reference"],
            ["kftrack `jit(lambda z: kalman_filter(z, ...).x)`: means only", cell(j["jit_means"]),
             "vs dynamax means only: " + ratio(j["jit_means"], j["dyn_means"], 1.0) + "; vs the direct call: "
             + ratio(j["jit_means"], j["direct_post"], 1.0), diff(j["jit_means"], b)],
            ["dynamax `jit(vmap(lgssm_filter(...).filtered_means))`", cell(j["dyn_means"]), "",
             diff(j["dyn_means"], bb)],
            ["kftrack `jit(...)` returning x, P, loglik (`priors=False`): full posterior", cell(j["jit_full"]),
             "vs dynamax full posterior: " + ratio(j["jit_full"], j["dyn_full"], 1.0), diff(j["jit_full"], b)],
            ["dynamax `jit(vmap(lgssm_filter))` returning means, covariances, loglik", cell(j["dyn_full"]), "",
             diff(j["dyn_full"], bb)],
            ["kftrack `jit(grad)` of the total log-likelihood (`tuning.total_loglik`) wrt (log q, log r)",
             cell(g["kf_grad"]),
             "vs dynamax: " + ratio(g["kf_grad"], g["dyn_grad"], 1.0) + "; vs its own forward pass: "
             + ratio(g["kf_grad"], g["kf_loglik"]), "the reference"],
            ["dynamax `jit(grad)` of the summed `marginal_loglik`", cell(g["dyn_grad"]),
             "vs its own forward pass: " + ratio(g["dyn_grad"], g["dyn_loglik"]),
             diff(g["dyn_grad"]) + " of the gradient"],
            ["kftrack `jit` of the total log-likelihood (`tuning.total_loglik`, forward)", cell(g["kf_loglik"]),
             "vs dynamax: "
             + ratio(g["kf_loglik"], g["dyn_loglik"]), ""],
            ["dynamax `jit` of the summed `marginal_loglik` (forward)", cell(g["dyn_loglik"]), "",
             diff(g["dyn_loglik"]) + " of the log-likelihood"],
        ]
        L.append(md_table(["call", "steps/s, median (min–max)", "ratio of medians (range)",
                           "agreement with the direct call"], rows))
        L.append("")
    if v:
        L.append(f"**vmap over {v['n_q']} values of q** ({v['runs']} runs × {v['steps']} steps each): "
                 f"`jit(vmap(q -> kalman_filter(...).x))` {cell(v['vmap_q'])} steps/s, {v['n_q']} direct calls "
                 f"{cell(v['direct_q'])}: {ratio(v['vmap_q'], v['direct_q'], 1.0)}; the two agree "
                 f"{diff(v['vmap_q'], v['vmap_q']['bound'])}.")
        L.append("")
    if im:
        L.append(f"**The IMM under grad** (3 modes, {im['runs']} runs × {im['steps']} steps, gradient with respect to "
                 "the 3 log noise levels and the 9 logits of the Markov matrix): forward "
                 "`jit(imm_loglik(..., sequence=False))` "
                 f"{cell(im['imm_forward'])} steps/s (compile {im['imm_forward']['compile_s']:.0f} s), `jit(grad)` "
                 f"{cell(im['imm_grad'])} steps/s (compile {im['imm_grad']['compile_s']:.0f} s): the gradient costs "
                 f"{im['imm_forward']['median'] / im['imm_grad']['median']:.1f}× the forward pass (ratio of the "
                 f"medians; range {im['imm_forward']['min'] / im['imm_grad']['max']:.1f}–"
                 f"{im['imm_forward']['max'] / im['imm_grad']['min']:.1f}).")
        L.append("")
    if p:
        L.append("**Parallel in time**, one run of T steps, filtered means inside `jit` (steps/s, median (min–max); "
                 "sequential: kftrack's JAX engine, `kalman_filter(..., missing=False, priors=False)`, and dynamax's "
                 "`lgssm_filter`); \"rel. diff.\": the largest relative difference of the filtered means from "
                 "kftrack's NumPy engine; compile: the first call's excess over the median:")
        L.append("")
        rows = []
        for TT, m in p.items():
            rows.append([f"{int(TT):,}", cell(m["kf_sequential"]), cell(m["kf_parallel"]), cell(m["dyn_sequential"]),
                         cell(m["dyn_parallel"]), ratio(m["kf_parallel"], m["kf_sequential"]),
                         ratio(m["kf_parallel"], m["dyn_parallel"]),
                         f"kftrack {diff(m['kf_parallel'])}, dynamax {diff(m['dyn_parallel'])}",
                         f"{m['kf_parallel']['compile_s']:.0f} s / {m['dyn_parallel']['compile_s']:.0f} s"])
        L.append(md_table(["T", "kftrack sequential", "kftrack `parallel_filter`", "dynamax sequential",
                           "dynamax `parallel_inference`", "kftrack parallel / sequential",
                           "kftrack parallel / dynamax parallel", "rel. diff. of the means",
                           "compile: kftrack / dynamax parallel"], rows))
        L.append("")
    if mm:
        mb = lambda b: f"{b / 1e6:.3g} MB"  # noqa: E731
        L.append(f"**Memory at long T** ({mm['runs']} runs × T steps, the model and parameters of the grad rows): "
                 "the temporary memory of the compiled program (XLA's `memory_analysis()`: its buffer assignment, "
                 "computed by the compiler for the program, not measured while it runs; "
                 f"JAX {mm.get('jax', '?')}, CPU; the arguments, the data and the parameters, come on top) of "
                 "`jit(tuning.total_loglik)` (forward), of `jit(grad)` of it with respect to (log q, log r), and "
                 "of `jit(grad)` with `checkpoint=c` (segments of c = round(√T) steps under "
                 f"`jax.checkpoint`); the gradient's steps/s both ways, median of {mm['repeats']} repeats (min–max), "
                 "and the largest relative difference of the two gradients:")
        L.append("")
        rows = []
        for TT, m in ((k, v) for k, v in mm.items() if k not in ("runs", "repeats", "jax")):
            by = m["bytes"]
            if by["grad"] is None:
                mem_cells = ["not reported by this backend"] * 4 + [""]
            else:
                mem_cells = [mb(by["forward"]["temp"]), mb(by["grad"]["temp"]), mb(by["grad_ckpt"]["temp"]),
                             f"{by['grad']['temp'] / by['grad_ckpt']['temp']:.1f}×", mb(by["grad"]["argument"])]
            rows.append([f"{int(TT):,}", str(m["c"]), *mem_cells, cell(m["grad"]), cell(m["grad_ckpt"]),
                         ratio(m["grad_ckpt"], m["grad"]), diff(m["grad_ckpt"])])
        L.append(md_table(["T", "c", "forward: temp", "grad: temp", "grad, checkpoint=c: temp",
                           "temp, grad / checkpointed", "arguments", "grad steps/s", "grad, checkpoint=c steps/s",
                           "speed, checkpointed / plain", "gradients' rel. diff."], rows))
        L.append("")
    if "total_s" in res:
        L.append(f"Total {res['total_s']:.0f} s.")
    L.append("")
    return "\n".join(L)


if __name__ == "__main__":
    main()
