"""The numba kernels' source, generated from one template of each step of the constant-step marcher.

The algorithm is :class:`impls.core.rootfind.MarchRefine` with a ``ConstantStep`` rule: ``init``
(φ at the start), ``step_march`` (one step Δ, clamped to the ray's bound ``hi``), ``step_ladder``
(``ladder`` steps evaluated together, judged pair by pair) and ``step_refine`` (the refiner's
proposal c in the bracket [a, b], φ(c), the bracket update and the reported depth; where φ's
rounding is modelled, ``vfy``, the certified bracket [A, B] and the verification of a closed
bracket, ``VERIFY``, whose rows evaluate the verification's sample instead), with the
refiners ``Bisect`` (c = (a + b)/2), ``Secant`` (c = t − φ(t)(t − p)/(φ(t) − φ(p))) and ``Newton``
(c = t − φ(t)/φ'(t)), the last two safeguarded as ``_OneSided.propose`` (a step shorter than
max(xtol/2, two float spacings of t) lengthened, after Brent, *Algorithms for Minimization without Derivatives*, 1973, ch. 4;
bisection where the iterate leaves the bracket or the bracket stalls, after rtsafe, Press et al.,
*Numerical Recipes*, 3rd ed. 2007, §9.4).
Each step is written here once, for one ray, with the same operations in the same order as the
array step (floating-point results depend on the order), so the kernels give the array drivers'
depths, statuses and counts.

A ray's iteration has one shape: the point its phase evaluates next (−1: the start, ``init``;
0: a march step; 2: a refinement step), φ there, and the update of its state by that phase's
step; the ladder (phase 1) evaluates ``ladder`` points and has its own block.  Two kernels are
generated from these templates by renaming the ray's variables (the suffix ``_K``):

- ``march_one`` (suffix empty): one ray to completion, every refiner and the ladder, φ and dφ/dt
  (:func:`impls.numba.derivatives.make_ray_eval`) where the refiner is Newton's;
- ``chunk_lanes`` (suffixes ``_0`` … ``_{LANES-1}``): ``LANES`` rays stepped in turn by one
  thread, each lane taking the next ray of its chunk when its ray finishes, for the marchers
  without a ladder, every refiner (Newton's with φ and dφ/dt: one kernel per scene structure for
  the three marchers; its own kernel, ``march_one``, had cost ~3 s of numba's compile per
  structure, for the same bits and run times: docs/performance.md).  A ray's steps form one
  chain of dependent operations (φ's square roots, the secant's divisions), so a loop over one
  ray waits on their latency; rays
  are independent, so stepping several in turn gives the processor independent work to overlap.
  Each lane's state is its own local variables, which numba keeps in registers (a state passed
  through function calls or arrays is slower), and each lane calls φ, or φ and dφ/dt, at one
  place (LLVM inlines it).

The variants differ only in what is not arithmetic: the evaluation (``@EVAL``: φ, or φ and dφ/dt
where ``deriv``), the flag ``use_ladder`` (a constant in the lanes kernel, so the compiler drops
its branches), and how a ray starts and finishes (arguments and a return, or a fetch from the
chunk and a write to the outputs).
"""

from __future__ import annotations

import re
import textwrap

#: rays stepped in turn by one thread (2 measured fastest of 2, 3, 4 and 8: more lanes spill registers)
LANES = 2
#: rays per parallel chunk of the lanes kernel (each chunk is one prange iteration, shared out by the lanes)
CHUNK = 256

#: the algorithm's numbers, read from the configuration arrays (:func:`impls.numba.driver.configuration`)
HEAD = """
t_min, t_max, xtol, leps, scale = fc[F_TMIN], fc[F_TMAX], fc[F_XTOL], fc[F_LEPS], fc[F_SCALE]
has_check, refiner = ic[I_HASCHECK] != 0, ic[I_REFINER]
max_steps, use_bounds = ic[I_MAXSTEPS], ic[I_BOUNDS] != 0
step, check = fc[F_STEP], fc[F_CHECK]
ladder, ladder_after = ic[I_LADDER], ic[I_LADDER_AFTER]
cover, rcoef = ic[I_COVER] != 0, fc[F_RES]
vfy = has_check and rcoef > 0.0
hh = 0.5 * xtol
sp2 = 2.0 * 2.220446049250313e-16  # two float64 spacings per unit of |t| (the kernels run float64)
"""

#: a ray's state (typed before the loop)
STATE = """
it_K, ne_K, ph_K, st_K = 0, 0, 0, IN
t_K = f_K = df_K = tp_K = fp_K = a_K = fa_K = b_K = hi_K = wq_K = mag_K = 0.0
te_K = fe_K = dfe_K = mid_K = 0.0
i2_K = False
g_K = 0.0
A_K = B_K = zl_K = zr_K = wd_K = rc0_K = rc1_K = 0.0
vm_K = lft_K = False
"""

#: impls.core.rootfind._start: the ray's range (t, hi) and status before any evaluation; φ at t
#: is the ray's next evaluation (phase −1)
START = """
t_K, hi_K, st_K = start(p, o0_K, o1_K, o2_K, d0_K, d1_K, d2_K, t_min, t_max, use_bounds)
ph_K, it_K, ne_K = -1, 0, 0
g_K = inf if cover else t_K
"""

#: one iteration of phases −1 (init), 0 (step_march) and 2 (step_refine): the next point te,
#: φ (and dφ/dt) there, the update
STEP = """
if ph_K == -1:
    te_K = t_K
elif ph_K == 0:
    te_K = _min(t_K + step, hi_K)
elif vm_K:
    wd_K = cwidth(t_K, mag_K, rcoef, xtol)
    lft_K = zl_K - A_K >= B_K - zr_K
    lo_K = A_K if lft_K else zr_K
    hi2_K = zl_K if lft_K else B_K
    mid_K = 0.5 * (lo_K + hi2_K)
    if lft_K:
        te_K = zl_K - 0.5 * wd_K
        if not (te_K > mid_K):
            te_K = mid_K
    else:
        te_K = zr_K + 0.5 * wd_K
        if not (te_K < mid_K):
            te_K = mid_K
else:
    mid_K = 0.5 * (a_K + b_K)
    i2_K = it_K % 3 == 0
    if refiner == 0:
        te_K = mid_K
    else:
        if deriv:
            te_K = t_K - f_K / df_K
        else:
            te_K = t_K - f_K * (t_K - tp_K) / (f_K - fp_K)
        stp_K = abs(te_K - t_K)
        hh_K = _max(hh, sp2 * abs(t_K))
        lift_K = stp_K + 0.5 * hh_K
        if stp_K < hh_K:
            te_K = t_K + lift_K if t_K - a_K <= b_K - t_K else t_K - lift_K
        slow_K = i2_K and (b_K - a_K > 0.5 * wq_K)
        if not ((te_K >= a_K) and (te_K <= b_K) and not slow_K):
            te_K = mid_K
@EVAL te_K fe_K dfe_K
ne_K += cost
if ph_K == -1:
    if not math.isfinite(fe_K):
        st_K = NONF
    elif fe_K == 0:
        st_K = UNC
    else:
        f_K, df_K = fe_K, dfe_K
        mag_K = ((abs(o0_K) + abs(o1_K)) + abs(o2_K)) + scale
        tp_K, fp_K, a_K, fa_K, b_K = t_K, f_K, t_K, f_K, t_K
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
    if cover and not cross_K and g_K == inf:
        if not covered(f_K, t_K, fe_K, te_K, te_K - t_K, check, mag_K, rcoef):
            g_K = t_K + rcert(f_K, t_K, check, mag_K, rcoef)
    um_K = miss_K and g_K < inf
    if has_check:
        rc0_K, rc1_K = rcert(f_K, t_K, check, mag_K, rcoef), rcert(fe_K, te_K, check, mag_K, rcoef)
        un0_K, un1_K = rc0_K == 0.0, rc1_K == 0.0
    else:
        un0_K, un1_K = f_K == 0, zero_K
    un_K = cross_K and (un0_K or un1_K)
    lt_K = conv_K and (g_K + step < t_K)
    if vfy and cross_K:  # (vfy: has_check) the certified bracket of the crossing step
        A_K, B_K = t_K + rc0_K, te_K - rc1_K
        zl_K, zr_K, vm_K = A_K, A_K, False
    it_K += 1
    st_K = verdict(nonf_K, conv_K, it_K >= max_steps, miss_K and not um_K, lv_K, um_K or lt_K or un_K)
    ph_K = 2 if cross_K else (1 if (use_ladder and it_K >= ladder_after) else 0)
    tp_K, fp_K, a_K, fa_K, b_K = t_K, f_K, t_K, f_K, te_K
    if refiner != 0:
        wq_K = 4.0 * (te_K - t_K)
    t_K, f_K, df_K = te_K, fe_K, dfe_K
    if um_K:
        t_K = inf
    elif un_K and not un1_K:
        t_K = tp_K
else:
    same_K = (fe_K > 0) == (fa_K > 0)
    ex_K = fe_K == 0
    na_K = te_K if (same_K or ex_K) else a_K
    nb_K = b_K if (same_K and not ex_K) else te_K
    nmid_K = 0.5 * (na_K + nb_K)
    conv_K = ex_K or (nb_K - na_K <= xtol) or (nmid_K <= na_K) or (nmid_K >= nb_K)
    if refiner == 0:
        to_K = te_K
    else:
        z_K = te_K - fe_K * (te_K - t_K) / (fe_K - f_K)
        z_K = _min(_max(z_K, na_K), nb_K)
        to_K = z_K if (conv_K and (fe_K != 0) and (z_K == z_K)) else te_K
    it_K += 1
    nonf_K = not math.isfinite(fe_K)
    if not vfy:
        lt_K = conv_K and (g_K + step < na_K)
        st_K = verdict(nonf_K, conv_K, it_K >= max_steps, False, False, lt_K)
        if refiner != 0 and i2_K:
            wq_K = b_K - a_K
        tp_K, fp_K = t_K, f_K
        a_K, b_K = na_K, nb_K
        t_K, f_K, df_K = to_K, fe_K, dfe_K
    else:
@VERIFY
"""

#: phase 2 where the march verifies its answers (impls.core.rootfind.MarchRefine.verifies: a bound
#: and φ's rounding modelled), inside STEP's refinement: the certified bracket [A, B] after the sample
#: (MarchRefine._bracket_sample), then for a row in verification mode MarchRefine._verify, for the
#: others the closed bracket's check against the closing width (MarchRefine._refine_verified)
VERIFY = """
q_K = abs(fe_K) * check
res_K = rcoef * (abs(te_K) + mag_K)
rc_K = _max(q_K - res_K, 0.0)
ur_K = q_K <= res_K
nA_K = _max(A_K, te_K + rc_K) if ((not ur_K) and same_K) else A_K
nB_K = _min(B_K, te_K - rc_K) if ((not ur_K) and not same_K) else B_K
A_K, B_K = nA_K, nB_K
if vm_K:
    th_K = (not ur_K) and (same_K != lft_K)
    if ur_K and lft_K:
        zl_K = _min(zl_K, te_K)
    if ur_K and not lft_K:
        zr_K = _max(zr_K, te_K)
    dn_K = (not ur_K) and (same_K == lft_K) and (B_K - A_K <= wd_K)
    lf2_K = zl_K - A_K >= B_K - zr_K
    lo_K = A_K if lf2_K else zr_K
    hi2_K = zl_K if lf2_K else B_K
    mid_K = 0.5 * (lo_K + hi2_K)
    gu_K = (not dn_K) and (not th_K) and ((zr_K - zl_K >= wd_K) or (mid_K <= lo_K) or (mid_K >= hi2_K))
    tc_K = _min(_max(t_K, A_K), B_K)
    gu_K = gu_K or (dn_K and (g_K + step < _min(A_K, tc_K)))
    st_K = verdict(nonf_K, dn_K and not gu_K, it_K >= max_steps, False, False, gu_K)
    if th_K:  # refinement resumes beyond the sample (its width check afresh: on_bracket)
        tp_K, fp_K = t_K, f_K
        a_K = _min(a_K, A_K) if lft_K else na_K
        b_K = nb_K if lft_K else _max(b_K, B_K)
        if refiner != 0:
            wq_K = 4.0 * (b_K - a_K)
        t_K, f_K, df_K = te_K, fe_K, dfe_K
        vm_K = False
    else:
        if dn_K:
            t_K = tc_K
            a_K = _min(A_K, tc_K)
            b_K = _max(B_K, tc_K)
        vm_K = not dn_K and not gu_K
else:
    okc_K = conv_K and (B_K - A_K <= cwidth(to_K, mag_K, rcoef, xtol))
    if refiner != 0 and i2_K:
        wq_K = b_K - a_K
    tp_K, fp_K = t_K, f_K
    t_K, f_K, df_K = to_K, fe_K, dfe_K
    a_K, b_K = na_K, nb_K
    if okc_K:
        tc_K = _min(_max(t_K, A_K), B_K)
        t_K = tc_K
        a_K = _min(A_K, tc_K)
        b_K = _max(B_K, tc_K)
    vm_K = conv_K and not okc_K
    zl_K, zr_K = t_K, t_K
    st_K = verdict(nonf_K, okc_K, it_K >= max_steps, False, False, okc_K and (g_K + step < a_K))
"""
STEP = STEP.replace("@VERIFY", textwrap.indent(textwrap.dedent(VERIFY).strip("\n"), " " * 8))

#: phase 1 (step_ladder): samples t + jΔ, j = 1 … ladder (clamped to hi), evaluated together, the
#: pairs judged in order as march steps, each one step against max_steps (the pairs past the budget
#: left, or past the first sample at hi, are not judged); the ray stops at the first pair that
#: crosses, is not finite or breaks the Lipschitz check, else moves to the last sample judged
LADDER = """
ts_K, fs_K, dfs_K = np.empty(ladder), np.empty(ladder), np.empty(ladder)
for j in range(ladder):
    ts_K[j] = _min(t_K + step * float(j + 1), hi_K)
    @EVAL ts_K[j] fs_K[j] dfs_K[j]
nj_K = min(ladder, max_steps - it_K)
e_K = nj_K - 1
stopped_K = False
cross_e_K = False
fin_e_K = True
lv_e_K = False
tq_K, fq_K = t_K, f_K
for j in range(nj_K):
    tj_K, fj_K = ts_K[j], fs_K[j]
    crossj_K = (fj_K == 0) or ((fj_K > 0) != (fq_K > 0))
    finj_K = math.isfinite(fj_K)
    event_K = crossj_K or not finj_K
    lvj_K = has_check and lipv(fq_K, fj_K, tq_K, tj_K, check, mag_K, leps)
    event_K = event_K or lvj_K
    if event_K:
        e_K, stopped_K, cross_e_K, fin_e_K, lv_e_K = j, True, crossj_K, finj_K, lvj_K
        break
    if cover and g_K == inf:
        if not covered(fq_K, tq_K, fj_K, tj_K, tj_K - tq_K, check, mag_K, rcoef):
            g_K = tq_K + rcert(fq_K, tq_K, check, mag_K, rcoef)
    if tj_K >= hi_K:
        e_K = j
        break
    tq_K, fq_K = tj_K, fj_K
te_K, fe_K = ts_K[e_K], fs_K[e_K]
tpe_K = t_K if e_K == 0 else ts_K[e_K - 1]
fpe_K = f_K if e_K == 0 else fs_K[e_K - 1]
dfpe_K = df_K if e_K == 0 else dfs_K[e_K - 1]
nonf_K = stopped_K and (not fin_e_K) and math.isfinite(te_K)
lv_K = stopped_K and lv_e_K
onto_K = cross_e_K or not stopped_K
miss_K = ((not stopped_K) and (te_K >= hi_K)) or not math.isfinite(te_K)
conv_K = cross_e_K and ((fe_K == 0) or (te_K - tpe_K <= xtol))
um_K = miss_K and g_K < inf
if has_check:
    rc0_K, rc1_K = rcert(fpe_K, tpe_K, check, mag_K, rcoef), rcert(fe_K, te_K, check, mag_K, rcoef)
    un0_K, un1_K = rc0_K == 0.0, rc1_K == 0.0
else:
    un0_K, un1_K = fpe_K == 0, fe_K == 0
un_K = cross_e_K and (un0_K or un1_K)
lt_K = conv_K and (g_K + step < tpe_K)
if vfy and cross_e_K:  # (vfy: has_check) the certified bracket of the crossing pair
    A_K, B_K = tpe_K + rc0_K, te_K - rc1_K
    zl_K, zr_K, vm_K = A_K, A_K, False
it_K += e_K + 1
ne_K += cost * ladder
st_K = verdict(nonf_K, conv_K, it_K >= max_steps, miss_K and not um_K, lv_K, um_K or lt_K or un_K)
tn_K = te_K if (onto_K and not (un_K and not un1_K)) else tpe_K
fn_K = fe_K if onto_K else fpe_K
tp_K, fp_K, a_K, fa_K, b_K = tpe_K, fpe_K, tpe_K, fpe_K, tn_K
ph_K = (1 if cross_e_K else 0) + 1
if refiner != 0:
    wq_K = 4.0 * (te_K - tpe_K)
if deriv:
    df_K = dfs_K[e_K] if onto_K else dfpe_K
t_K, f_K = tn_K, fn_K
if um_K:
    t_K = inf
"""

_RAY = "p, o0_K, o1_K, o2_K, d0_K, d1_K, d2_K"

_ONE_RAY = """
def march_one(p, o0, o1, o2, d0, d1, d2, fc, ic):
    \"\"\"One ray of MarchRefine with a ConstantStep rule: (t as reported, status, iterations, evaluations).\"\"\"
{head}
    deriv = refiner == 2
    cost = 3 if deriv else 1
    use_ladder = ladder > 1
{state}
{start}
    if st_K == IN:
        while True:
            if ph_K == 1:
{ladder}
            else:
{step}
            if st_K != IN:
                break
    return final_t(t_K, st_K), st_K, it_K, ne_K


def run_march(O, D, p, fc, ic, out_t, out_s, out_i, out_e):
    for i in prange(O.shape[0]):
        t, s, it, ne = march_one_jit(p, O[i, 0], O[i, 1], O[i, 2], D[i, 0], D[i, 1], D[i, 2], fc, ic)
        out_t[i], out_s[i], out_i[i], out_e[i] = t, s, it, ne
"""

_LANES_HEAD = """
def chunk_lanes(O, D, p, fc, ic, out_t, out_s, out_i, out_e, nxt, stop):
    \"\"\"Rays nxt … stop − 1 of MarchRefine with a ConstantStep rule, without ladder steps.\"\"\"
{head}
    if ladder > 1:
        raise ValueError("the lanes kernel runs no ladder stage: march_one does")
    deriv = refiner == 2
    cost = 3 if deriv else 1
    use_ladder = False
"""

_LANE_STATE = """
act_K = False
i_K = 0
o0_K = o1_K = o2_K = d0_K = d1_K = d2_K = 0.0
"""

_FETCH = """
if not act_K:
    while nxt < stop and not act_K:
        i_K = nxt
        nxt += 1
        o0_K, o1_K, o2_K = O[i_K, 0], O[i_K, 1], O[i_K, 2]
        d0_K, d1_K, d2_K = D[i_K, 0], D[i_K, 1], D[i_K, 2]
{start}
        if st_K == IN:
            act_K = True
        else:
            out_t[i_K], out_s[i_K], out_i[i_K], out_e[i_K] = final_t(t_K, st_K), st_K, it_K, ne_K
if act_K:
    busy = True
{step}
    if st_K != IN:
        out_t[i_K], out_s[i_K], out_i[i_K], out_e[i_K] = final_t(t_K, st_K), st_K, it_K, ne_K
        act_K = False
"""

_LANES_TAIL = """

def run_lanes(O, D, p, fc, ic, out_t, out_s, out_i, out_e):
    n = O.shape[0]
    for c in prange((n + CHUNK - 1) // CHUNK):
        chunk_lanes_jit(O, D, p, fc, ic, out_t, out_s, out_i, out_e, c * CHUNK, min(c * CHUNK + CHUNK, n))
"""

#: how the kernels are compiled (the names the kernels call: march_one_jit, chunk_lanes_jit);
#: ``{parallel}``: whether the outer loops are numba's parallel ``prange`` (:func:`source`)
_JIT = """
march_one_jit = njit(error_model="numpy")(march_one)
run_march = njit(parallel={parallel}, error_model="numpy")(run_march)
chunk_lanes_jit = njit(error_model="numpy")(chunk_lanes)
run_lanes = njit(parallel={parallel}, error_model="numpy")(run_lanes)
"""

_SUFFIX = re.compile(r"_K\b")
_EVAL = re.compile(r"^(?P<ind> *)@EVAL (?P<t>\S+) (?P<f>\S+) (?P<df>\S+)$", re.M)


def _expand(text: str, deriv: bool) -> str:
    """``@EVAL t f df``: f = φ(o + t d), and where ``deriv`` (a run-time flag) also df = dφ/dt."""

    def one(m):
        ind, t, f, df = m["ind"], m["t"], m["f"], m["df"]
        phi = f"{ind}{f} = ev({_RAY}, {t})"
        if not deriv:
            return phi
        return f"{ind}if deriv:\n{ind}    {f}, {df} = ev_d({_RAY}, {t})\n{ind}else:\n    {phi}"

    return _EVAL.sub(one, text)


def _lane(text: str, suffix: str, indent: int, deriv: bool = False) -> str:
    """A template for one ray: ``_K`` made ``suffix`` (the ray's variables), evaluations expanded,
    indented by ``indent`` spaces."""
    body = _expand(textwrap.dedent(text).strip("\n"), deriv)
    return textwrap.indent(_SUFFIX.sub(suffix, body), " " * indent)


def one_ray_source() -> str:
    """``march_one`` (one ray: every refiner, the ladder, derivatives) and ``run_march`` (rays in
    a prange loop, calling ``march_one_jit``, the compiled ``march_one``)."""
    text = _ONE_RAY.format(head=_lane(HEAD, "_K", 4), state=_lane(STATE, "_K", 4), start=_lane(START, "_K", 4),
                           ladder=_lane(LADDER, "_K", 16, deriv=True), step=_lane(STEP, "_K", 16, deriv=True))
    return _SUFFIX.sub("", text)


def lanes_source(lanes: int = LANES) -> str:
    """``chunk_lanes(…, nxt, stop)`` (rays nxt … stop − 1 in ``lanes`` lanes) and ``run_lanes``
    (every chunk of ``CHUNK`` rays in a prange loop, calling ``chunk_lanes_jit``)."""
    parts = [_LANES_HEAD.format(head=_lane(HEAD, "", 4))]
    for k in range(lanes):
        parts.append(_lane(STATE + _LANE_STATE, f"_{k}", 4) + "\n")
    parts.append("    while True:\n        busy = False\n")
    for k in range(lanes):
        fetch = _FETCH.format(start=_lane(START, "_K", 8), step=_lane(STEP, "_K", 4, deriv=True))
        parts.append(_lane(fetch, f"_{k}", 8) + "\n")
    parts.append("        if not busy:\n            break\n")
    parts.append(_LANES_TAIL)
    return "".join(parts)


def source(parallel: bool = True) -> str:
    """The module text of both kernels, compiled (:data:`_JIT`); its globals are those of
    :func:`impls.numba.driver._make_kernels` (φ, the helper steps, the configuration's index names).
    ``parallel``: the rays' loops are numba's parallel ``prange`` (threads); False, a plain loop
    (``prange`` is ``range`` there), for one thread."""
    return "\n".join([one_ray_source(), lanes_source(), _JIT.format(parallel=bool(parallel))])
