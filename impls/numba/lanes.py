"""Interleaved per-ray loops: ``LANES`` rays stepped in turn by one thread, for the constant-step
marchers without a ladder stage and without derivatives (the certified methods run the core
array algorithm: :func:`impls.numba.driver._run_certified`).

A ray's steps form one chain of dependent operations (φ's square roots, the secant's divisions),
so a per-ray loop waits on their latency; rays are independent, so stepping several in turn gives
the processor independent work to overlap.  The kernel is Python source generated here, one copy
of the step per lane with the lane's own variables (numba keeps them in registers; a state
passed through function calls or arrays measured slower), and compiled by numba per scene like
the per-ray kernels of :mod:`impls.numba.driver`.  Each lane runs exactly
``driver``'s ``march_one`` for one ray at a time — the same operations in the same order, so the
same results — and takes the next ray of its thread's chunk when its ray finishes.  A lane's
iteration computes the depth its phase evaluates next (−1: the start, ``init``; 0: a march step;
1: a refinement step), evaluates φ there (one inlined copy of φ per lane, which keeps the
compile time down), and updates its state as that phase's step does.
"""

from __future__ import annotations

#: rays stepped in turn by one thread (2, 3, 4 and 8 measured: 2 fastest, 8 slowest — register spills)
LANES = 2
#: rays per parallel chunk (each chunk is one prange iteration, shared out by the lanes)
CHUNK = 256

_FETCH = """
            if not act_K:
                while nxt < stop and not act_K:
                    i_K = nxt
                    nxt += 1
                    o0_K, o1_K, o2_K = O[i_K, 0], O[i_K, 1], O[i_K, 2]
                    d0_K, d1_K, d2_K = D[i_K, 0], D[i_K, 1], D[i_K, 2]
                    t_K, hi_K, st_K = start(p, o0_K, o1_K, o2_K, d0_K, d1_K, d2_K, t_min, t_max, use_bounds)
                    if st_K == IN:  # φ at t is the lane's next evaluation (phase -1: MarchRefine.init)
                        ph_K, it_K, ev_K = -1, 0, 0
                        act_K = True
                    else:
                        out_t[i_K], out_s[i_K], out_i[i_K], out_e[i_K] = final_t(t_K, st_K), st_K, 0, 0
"""

_STEP = """
            if act_K:
                busy = True
                if ph_K == -1:
                    te_K = t_K
                elif ph_K == 0:
                    te_K = _min(t_K + step, hi_K)
                else:
                    mid_K = 0.5 * (a_K + b_K)
                    i2_K = it_K % 3 == 0
                    if refiner == 0:
                        te_K = mid_K
                    else:
                        te_K = t_K - f_K * (t_K - p_K) / (f_K - fp_K)
                        stp_K = abs(te_K - t_K)
                        lift_K = stp_K + 0.5 * hh
                        if stp_K < hh:
                            te_K = t_K + lift_K if t_K - a_K <= b_K - t_K else t_K - lift_K
                        slow_K = i2_K and (b_K - a_K > 0.5 * wq_K)
                        if not ((te_K >= a_K) and (te_K <= b_K) and not slow_K):
                            te_K = mid_K
                fe_K = ev(p, o0_K, o1_K, o2_K, d0_K, d1_K, d2_K, te_K)
                ev_K += 1
                if ph_K == -1:
                    if not math.isfinite(fe_K):
                        st_K = NONF
                    elif fe_K == 0:
                        st_K = CONV
                    else:
                        f_K = fe_K
                        mag_K = ((abs(o0_K) + abs(o1_K)) + abs(o2_K)) + scale
                        p_K, fp_K, a_K, fa_K, b_K = t_K, f_K, t_K, f_K, t_K
                        wq_K, ph_K, it_K = inf, 0, 0
                elif ph_K == 0:
                    zero_K = fe_K == 0
                    fin_K = math.isfinite(fe_K)
                    cross_K = fin_K and (zero_K or ((fe_K > 0) != (f_K > 0)))
                    gone_K = (te_K >= hi_K) or not math.isfinite(te_K)
                    miss_K = (not cross_K) and gone_K
                    conv_K = cross_K and (zero_K or (te_K - t_K <= xtol))
                    nonf_K = (not fin_K) and math.isfinite(te_K)
                    lv_K = has_check and lipv(f_K, fe_K, t_K, te_K, check, mag_K, leps)
                    it_K += 1
                    st_K = verdict(nonf_K, conv_K, it_K >= max_steps, miss_K, lv_K)
                    ph_K = 1 if cross_K else 0
                    p_K, fp_K, a_K, fa_K, b_K = t_K, f_K, t_K, f_K, te_K
                    if refiner != 0:
                        wq_K = 4.0 * (te_K - t_K)
                    t_K, f_K = te_K, fe_K
                else:
                    same_K = (fe_K > 0) == (fa_K > 0)
                    na_K = te_K if same_K else a_K
                    nb_K = b_K if same_K else te_K
                    nmid_K = 0.5 * (na_K + nb_K)
                    conv_K = (fe_K == 0) or (nb_K - na_K <= xtol) or (nmid_K <= na_K) or (nmid_K >= nb_K)
                    if refiner == 0:
                        to_K = te_K
                    else:
                        z_K = te_K - fe_K * (te_K - t_K) / (fe_K - f_K)
                        z_K = _min(_max(z_K, na_K), nb_K)
                        to_K = z_K if (conv_K and (fe_K != 0) and (z_K == z_K)) else te_K
                    it_K += 1
                    st_K = verdict(not math.isfinite(fe_K), conv_K, it_K >= max_steps, False, False)
                    if refiner != 0 and i2_K:
                        wq_K = b_K - a_K
                    p_K, fp_K = t_K, f_K
                    a_K, b_K = na_K, nb_K
                    t_K, f_K = to_K, fe_K
                if st_K != IN:
                    out_t[i_K], out_s[i_K], out_i[i_K], out_e[i_K] = final_t(t_K, st_K), st_K, it_K, ev_K
                    act_K = False
"""

_INIT = """        act_K = False
        i_K, it_K, ev_K, ph_K, st_K = 0, 0, 0, 0, IN
        o0_K = o1_K = o2_K = d0_K = d1_K = d2_K = 0.0
        t_K = f_K = p_K = fp_K = a_K = fa_K = b_K = hi_K = wq_K = mag_K = 0.0
        te_K = fe_K = mid_K = 0.0
        i2_K = False
"""

_HEAD = """
def chunk_lanes(O, D, p, fc, ic, out_t, out_s, out_i, out_e, nxt, stop):
    t_min, t_max, xtol, leps, scale = fc[F_TMIN], fc[F_TMAX], fc[F_XTOL], fc[F_LEPS], fc[F_SCALE]
    has_check, refiner = ic[I_HASCHECK] != 0, ic[I_REFINER]
    max_steps, use_bounds = ic[I_MAXSTEPS], ic[I_BOUNDS] != 0
    step, check = fc[F_STEP], fc[F_CHECK]
    hh = 0.5 * xtol
    if True:
"""


def source(lanes: int = LANES) -> str:
    """The lanes kernel as Python source: ``chunk_lanes(…, nxt, stop)`` runs rays nxt … stop − 1 in
    ``lanes`` lanes; ``run_lanes(O, D, p, fc, ic, out_t, out_s, out_i, out_e)`` runs every chunk of
    ``CHUNK`` rays in a prange loop (calling ``chunk_lanes_jit``, the compiled ``chunk_lanes``)."""
    body = [_HEAD]
    body += [_INIT.replace("_K", f"_{k}") for k in range(lanes)]
    body.append("        while True:\n            busy = False\n")
    for k in range(lanes):
        body.append(_FETCH.replace("_K", f"_{k}"))
        body.append(_STEP.replace("_K", f"_{k}"))
    body.append("            if not busy:\n                break\n")
    body.append(_TAIL)
    return "".join(body)


_TAIL = """

def run_lanes(O, D, p, fc, ic, out_t, out_s, out_i, out_e):
    n = O.shape[0]
    for c in prange((n + CHUNK - 1) // CHUNK):
        chunk_lanes_jit(O, D, p, fc, ic, out_t, out_s, out_i, out_e, c * CHUNK, min(c * CHUNK + CHUNK, n))
"""
