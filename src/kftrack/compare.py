r"""A comparison of two methods over Monte Carlo runs that speaks for itself.

Numerics layer: pure functions and small immutable results, no plotting, no printing. This is
the library side of DESIGN.md, "How a sentence earns its claim": the sentence on a page and
the hidden assert below it come from one :class:`ComparisonResult`.

* :func:`compare_runs` takes per-run values of two methods, ``a`` and ``b`` (typically the
  per-run RMSE of two filters from :func:`kftrack.montecarlo.per_run_error`), and returns the
  estimate (a difference, or a ratio), its two-sided confidence interval, the standard error,
  the p-value, the smallest effect the runs could detect at 80 % power, and a verdict word:
  ``"lower"``, ``"higher"``, ``"equivalent within ±m"`` (TOST, when a margin is given) or
  ``"not resolved by N runs"``. A failure to reject is never read as equality (rule 2).
* :func:`holm` controls the family-wise error when one page makes several comparisons.
* :func:`compare_sweep` compares at every value of a parameter and says where the verdict
  flips (rules 1 and 3: name the configurations, or sweep the parameter that could change
  the answer).

Several comparisons on one page
-------------------------------
Each :func:`compare_runs` call holds its own error rate ``1 - level``. A page that makes ``k``
comparisons and draws a conclusion from each states so and passes them through :func:`holm`,
which returns the same results with Holm-adjusted p-values and verdicts (the family-wise error
of all the claims together is then at most ``1 - level``)::

    results = holm([compare_runs(rmse["IMM"], rmse[name], scale="log_ratio")
                    for name in ("CV", "CA", "Singer")])
    for r, name in zip(results, ("CV", "CA", "Singer")):
        print(r.sentence("IMM", name, "RMSE"))      # "... Holm over 3 tests ...: lower"
        assert r.verdict == "lower"                 # the hidden assert, from the same result

Alternatively the page states the level of each comparison and makes no joint claim.

Claims over a parameter range
-----------------------------
:func:`compare_sweep` calls ``fn(value) -> (a, b)`` for each value (seed every value the same
way, so the comparison is paired across values too) and returns one result per value and the
consecutive values between which the verdict changes. "A is lower at every value tried" is an
intersection of claims, each tested at ``level`` with no adjustment (it fails if any one
fails; Berger 1982); "A is lower here and not there" is several claims: ``adjust="holm"``.
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
from scipy import stats

from ._validate import as_float_array, check_finite

__all__ = ["ComparisonResult", "compare_runs", "HolmResult", "holm", "Sweep", "compare_sweep"]

_SCALES = ("difference", "log_ratio")
_POWER = 0.8  # the power at which the minimal detectable effect is stated
# Default round-off level for "no spread" (``rtol=None``): per-run values that differ only by
# round-off. Each value carries a relative error of at most a few dozen roundings of eps/2 from
# the code that made it, and the subtraction one more, so the differences of run i and run j,
# identical in exact arithmetic, differ by at most 64 eps (s_i + s_j), s_i = max(|a_i|, |b_i|)
# (logarithms: a relative error r of a value is an absolute error r of its logarithm, so
# s_i = max(|log a_i|, |log b_i|, 1)); anything wider is real spread and goes through the t
# test. Quantities computed through many more roundings (recursive filters) need a stated rtol.
_ROUNDOFF = 64 * float(np.finfo(float).eps)


@dataclass(frozen=True)
class ComparisonResult:
    r"""The comparison of per-run values ``a`` against ``b`` (:func:`compare_runs`).

    Two scales. **Reported** (what a sentence shows): ``estimate`` and ``ci``, a difference
    ``a - b`` or a ratio ``a / b``. **Analysis** (where the t statistic lives): ``delta``,
    ``se``, ``mde``, the difference itself, or the mean log ratio
    :math:`\overline{\log(a/b)}` (so ``se = 0.01`` is about a 1 % relative standard error and
    the ratios the runs could detect are ``exp(±mde)``).

    Attributes
    ----------
    estimate : mean difference (paired: :math:`\bar d`, :math:`d_i = a_i - b_i`; unpaired:
        :math:`\bar a - \bar b`), or ratio :math:`\exp(\overline{\log(a/b)})`, the geometric
        mean of the per-run ratios (unpaired: the ratio of the geometric means).
    ci : ``(low, high)`` two-sided confidence interval of ``estimate`` at ``level``:
        :math:`\delta \pm t_{1-\alpha/2,\nu}\,\mathrm{se}` (exponentiated for a ratio).
    se : standard error of ``delta``.
    p_value : two-sided p-value of :math:`H_0: \delta = 0` (ratio 1): the t test's, or an exact
        test's when ``exact``.
    mde : minimal detectable effect at 80 % power, on the analysis scale,
        :math:`(t_{1-\alpha/2,\nu} + t_{0.8,\nu})\,\mathrm{se}` (see :func:`compare_runs`).
    verdict : ``"lower"``, ``"higher"``, ``"equivalent within ±m"`` or
        ``"not resolved by N runs"`` (``"N + M runs"`` unpaired); ``"equal"`` only when
        ``exact`` and the difference is 0 in every run.
    delta : the estimate on the analysis scale (difference, or mean log ratio).
    df : degrees of freedom :math:`\nu` of the t distribution (``n - 1`` paired; Welch).
    level : confidence level, :math:`1 - \alpha`.
    n_a, n_b : runs of ``a`` and of ``b`` (equal when paired).
    paired : paired (same noise run by run) or unpaired (Welch).
    scale : ``"difference"`` or ``"log_ratio"``.
    margin : equivalence margin (``None``: no equivalence test); a ratio margin ``m`` means
        the ratio lies in ``(1 - m, 1 + m)``.
    equivalent : TOST outcome (``None`` without margin); may be True alongside ``"lower"``
        (a significant difference smaller than the margin).
    p_equivalence : TOST p-value, the larger of the two one-sided p-values (``None`` without
        margin).
    tests : number of tests in the Holm family (1: not adjusted, see :func:`holm`).
    p_adjusted, p_equivalence_adjusted : Holm-adjusted p-values (equal to the raw ones when
        ``tests == 1``); the verdict is computed from these.
    exact : the runs show no spread beyond round-off (paired: every run gives the same
        difference; unpaired: every run of each method gives the same value), so the
        difference on these runs is known exactly: ``se = mde = 0``, ``ci = (estimate,
        estimate)``; ``p_value`` is that of an exact test (paired: the sign test,
        :math:`2^{1-n}` for :math:`n` differences of one sign; unpaired: the permutation
        test, :math:`1/\binom{N}{n_a}`, twice that when :math:`n_a = n_b`), or 1 when the
        difference is 0 in every run (verdict ``"equal"``).
    tolerance : the round-off bound on the analysis scale, ``rtol`` times the largest
        :math:`s_i` (see :func:`compare_runs`); the exact estimate shows no digit below it.
    rtol : the round-off level stated by the caller (``None``: the default ``64 eps``).
    """

    estimate: float
    ci: tuple[float, float]
    se: float
    p_value: float
    mde: float
    verdict: str
    delta: float
    df: float
    level: float
    n_a: int
    n_b: int
    paired: bool
    scale: str
    margin: float | None
    equivalent: bool | None
    p_equivalence: float | None
    tests: int
    p_adjusted: float
    p_equivalence_adjusted: float | None
    exact: bool = False
    tolerance: float = 0.0
    rtol: float | None = None

    @property
    def n(self) -> int:
        """Runs: the number of pairs when paired, ``n_a + n_b`` when not."""
        return self.n_a if self.paired else self.n_a + self.n_b

    @property
    def kind(self) -> str:
        """The verdict without its numbers: ``"lower"``, ``"higher"``, ``"equivalent"``,
        ``"not resolved"`` or (exact results only) ``"equal"`` (for asserts and for
        :func:`compare_sweep`'s flips)."""
        return self.verdict.split(" within")[0].split(" by")[0]

    def sentence(self, name_a: str = "A", name_b: str = "B", quantity: str = "value", unit: str = "") -> str:
        """One honest line, e.g. ``"A's RMSE is 0.93× B's (95 % CI 0.90–0.96, 200 paired runs):
        lower"``.

        Every number is rounded at the decimal of the first significant digit of its standard
        error (for a ratio, ``estimate * se`` by the delta method), so no digit shown is noise;
        a bound that would round onto 0 (ratio 1) keeps the digits that show its side. An unresolved
        verdict adds the effects the runs could have detected at 80 % power; a Holm-adjusted
        result names its family and adjusted p-value.

        Parameters
        ----------
        name_a, name_b : the two methods, in the order of :func:`compare_runs`.
        quantity : what was measured per run (``"RMSE"``, ``"mean NEES"``).
        unit : unit of a difference (``"m"``); unused for a ratio.
        """
        ratio = self.scale == "log_ratio"
        if self.exact:
            return self._exact_sentence(name_a, name_b, quantity, unit)
        se = self.se * self.estimate if ratio else self.se
        u = f" {unit}" if unit and not ratio else ""
        ref = 1.0 if ratio else 0.0
        est, lo, hi = _fmt(self.estimate, se), _fmt(self.ci[0], se, ref), _fmt(self.ci[1], se, ref)
        interval = f"{lo}–{hi}" if self.ci[0] >= 0 else f"{lo} to {hi}"
        runs = f"{self.n_a} paired runs" if self.paired else f"{self.n_a} + {self.n_b} unpaired runs, Welch"
        where = f"{_pct(self.level)} CI {interval}{u}, {runs}{self._holm_text()}"
        head = (f"{name_a}'s {quantity} is {est}× {name_b}'s" if ratio
                else f"{name_a}'s {quantity} minus {name_b}'s is {est}{u}")
        if self.kind == "not resolved":
            m = _sig2(self.mde)
            word = self.verdict + (
                f" (80 % power only for ratios outside {_sig2(math.exp(-self.mde))}–{_sig2(math.exp(self.mde))})"
                if ratio else f" (80 % power only for differences beyond ±{m}{u})")
        else:
            word = self._word(u)
        return f"{head} ({where}): {word}"

    def _holm_text(self) -> str:
        """``"; Holm over k tests, adjusted p = ..."`` for a Holm-adjusted result, else ``""``."""
        if self.tests == 1:
            return ""
        p_adj = self.p_equivalence_adjusted if self.kind == "equivalent" else self.p_adjusted
        what = "TOST p" if self.kind == "equivalent" else "p"
        return f"; Holm over {self.tests} tests, adjusted {what} {_fmt_p(p_adj)}"

    def _word(self, u: str) -> str:
        """The verdict with its margin and unit (all kinds but "not resolved")."""
        ratio = self.scale == "log_ratio"
        if self.kind == "equivalent":
            return f"equivalent within ±{_margin_text(self.margin, ratio)}{u}"
        if self.equivalent and self.kind != "equal":
            return f"{self.verdict}, yet equivalent within ±{_margin_text(self.margin, ratio)}{u}"
        return self.verdict

    def _exact_sentence(self, name_a: str, name_b: str, quantity: str, unit: str) -> str:
        """The sentence of an exact result: the difference in every run, the exact test's p."""
        ratio = self.scale == "log_ratio"
        u = f" {unit}" if unit and not ratio else ""
        runs = f"{self.n_a} paired runs" if self.paired else f"{self.n_a} + {self.n_b} unpaired runs"
        to = "to round-off" if self.rtol is None else f"to the stated round-off {self.rtol:g}"
        if self.kind == "equal":  # a statement about these runs, not about the population
            one = "" if self.paired else "one value on every run of either method, "
            return (f"{name_a}'s {quantity} equals {name_b}'s in each of the {runs} "
                    f"({one}{to}; these runs only, no interval to compute): equal")
        tol = self.tolerance * self.estimate if ratio else self.tolerance
        est = _fmt_exact(self.estimate, tol)
        head = (f"{name_a}'s {quantity} is {est}× {name_b}'s" if ratio
                else f"{name_a}'s {quantity} minus {name_b}'s is {est}{u}")
        if self.paired:
            why = f"the same {'ratio' if ratio else 'difference'} in each of the {runs}, {to}; exact sign test"
        else:
            why = f"{runs}, each method the same value on every run, {to}; exact permutation test"
        why += f" p {_fmt_p(self.p_value)}{self._holm_text()}"
        word = self._word(u)
        if self.kind == "not resolved" and self.paired and self.tests == 1:
            alpha, k = 1.0 - self.level, 2
            while 2.0 ** (1 - k) >= alpha:
                k += 1
            word += f" (the sign test needs {k} runs of one sign for p < {alpha:.3g})"
        return f"{head} ({why}): {word}"

    def __str__(self) -> str:
        return self.sentence()


def compare_runs(a, b, *, paired: bool = True, scale: str = "difference", level: float = 0.95,
                 margin: float | None = None, rtol: float | None = None) -> ComparisonResult:
    r"""Compare per-run values ``a`` of one method with ``b`` of another: estimate, two-sided
    confidence interval, p-value, minimal detectable effect and a verdict word.

    Paired (default; the same noise in run ``i`` for both methods, so the run-to-run spread of
    the scenario cancels): :math:`d_i = g(a_i) - g(b_i)`, :math:`\delta = \bar d`,
    :math:`\mathrm{se} = s_d/\sqrt n`, :math:`\nu = n - 1` (``scipy.stats.ttest_rel``).
    Unpaired (independent samples, a stated option): Welch,
    :math:`\delta = \bar g(a) - \bar g(b)`, :math:`\mathrm{se}^2 = s_a^2/n_a + s_b^2/n_b`,
    :math:`\nu` by Welch–Satterthwaite (``ttest_ind(equal_var=False)``). Here :math:`g` is the
    identity (``scale="difference"``) or :math:`\log` (``scale="log_ratio"``: ratios such as
    RMSE ratios, whose sampling distribution is skewed on the ratio scale; the interval is
    computed for the mean log ratio and reported as a ratio).

    With :math:`\alpha = 1 - \mathrm{level}`:

    * confidence interval :math:`\delta \pm t_{1-\alpha/2,\nu}\,\mathrm{se}`; two-sided
      p-value :math:`2\,P(T_\nu > |\delta|/\mathrm{se})`;
    * minimal detectable effect :math:`\mathrm{mde} = (t_{1-\alpha/2,\nu} + t_{0.8,\nu})\,
      \mathrm{se}`: a true effect of this size is found (two-sided, level ``level``) with
      probability about 80 % by a repetition of the study with the same standard error
      (the shifted-t approximation of the noncentral t power; the exact power is 0.80 to
      within 0.01 for :math:`\nu \ge 5` at ``level=0.95``, 0.79 at :math:`\nu = 4`);
    * TOST (Schuirmann 1987), when ``margin`` is given: the equivalence region is
      :math:`(-m, m)` for a difference, the ratio in :math:`(1 - m, 1 + m)` for a ratio
      (bounds :math:`\log(1 \mp m)` on the analysis scale). Equivalence is concluded when
      both one-sided tests reject at level :math:`\alpha` (not :math:`\alpha/2`), that is,
      when the :math:`(1 - 2\alpha)` interval :math:`\delta \pm t_{1-\alpha,\nu}\,\mathrm{se}`
      (90 % for ``level=0.95``) lies strictly inside the region; its p-value is the larger
      one-sided p-value.

    Verdict: ``"lower"`` / ``"higher"`` (``a`` below / above ``b``) when ``p < alpha``, i.e.
    the interval excludes 0 (ratio 1); else ``"equivalent within ±m"`` when TOST concludes;
    else ``"not resolved by N runs"``. A boundary tie counts as not rejected. A significant
    difference smaller than the margin says ``"lower"`` with ``equivalent=True``. A one-sided
    claim fixed before the runs is the two-sided one at ``level = 1 - 2*alpha_one_sided``:
    say so on the page.

    No spread (``exact=True``): when every paired difference is the same up to round-off
    (unpaired: every value of ``a`` the same and every value of ``b`` the same), there is no
    run-to-run noise for a t test: the result says so instead of printing a zero-width
    interval (``se = mde = 0``, ``ci = (estimate, estimate)``). Runs ``i`` and ``j`` count as
    giving the same difference when :math:`|d_i - d_j| \le r\,(s_i + s_j)`, with
    :math:`s_i = \max(|a_i|, |b_i|)` (``log_ratio``: :math:`\max(|\log a_i|, |\log b_i|, 1)`)
    and the round-off level :math:`r` = ``rtol``, by default :math:`64\,\varepsilon`; a run's
    difference counts as 0 when :math:`|d_i| \le r\,s_i`. Zero spread can also happen by
    chance (0/1 or other discrete values), so the p-value is that of an exact test: paired, the
    sign test, :math:`p = 2^{1-n}` for :math:`n` non-zero differences of one sign (0.25 at
    :math:`n = 3`; ``level=0.95`` needs :math:`n \ge 6`); unpaired, the permutation test of
    the difference of means (Fisher's exact test for two values),
    :math:`p = 1/\binom{N}{n_a}`, twice that when :math:`n_a = n_b` (0.1 for 3 + 3). The
    verdict follows that p (``"not resolved"`` when it is too large), and :func:`holm` uses it;
    TOST uses the one-sided versions (:math:`2^{-n}`, :math:`1/\binom{N}{n_a}`) when the
    difference lies inside the region. Only when the difference is 0 in every run is the
    verdict ``"equal"``: no difference in any of these runs, not a population equality (for
    that, give a margin: the sign-test TOST then says whether the runs suffice).

    .. warning:: The default round-off level :math:`64\,\varepsilon` suits values computed
       through a few dozen roundings. Recursive computations accumulate more: the per-run
       outputs of a Kalman filter with the Joseph and with the short covariance update
       (identical in exact arithmetic) differ by about 1.4e-10 relative after 500 steps, and
       the t test reads that round-off as a result ("lower", p = 0.03). State the round-off
       level of such quantities with ``rtol`` (e.g. ``rtol=1e-9``): differences within it
       count as no difference.

    Parameters
    ----------
    a, b : (N,) and (M,) finite per-run values of the two methods, one value per run (1-D; a
        study with several quantities calls once per quantity, a parameter range goes through
        :func:`compare_sweep`). Paired: ``N == M`` and run ``i`` of ``a`` shares its noise
        with run ``i`` of ``b``. ``log_ratio``: all values > 0.
    paired : paired t (default) or Welch's unpaired t.
    scale : ``"difference"`` (``a - b``, in the unit of the values) or ``"log_ratio"``
        (``a / b``).
    level : two-sided confidence level, in (0, 1); > 0.5 when a margin is given.
    margin : equivalence margin ``m > 0`` (a difference in the unit of the values; for a
        ratio, a relative margin with ``0 < m < 1``: 0.05 means the ratio in (0.95, 1.05)),
        or ``None`` for no equivalence test.
    rtol : the relative round-off level of the values, in [0, 1) (``None``: ``64 eps``, a few
        dozen roundings); differences within it count as no difference (see the warning above).

    Returns
    -------
    ComparisonResult

    Examples
    --------
    Per-run RMSE of two filters on the same 8 noise runs; A's are about 10 % lower:

    >>> import numpy as np
    >>> b = np.array([1.00, 1.20, 0.90, 1.10, 1.05, 0.95, 1.15, 1.00])
    >>> a = 0.9 * b * np.array([1.01, 0.99, 1.02, 0.98, 1.00, 1.01, 0.99, 1.00])
    >>> r = compare_runs(a, b, scale="log_ratio")
    >>> print(r.sentence("A", "B", "RMSE"))
    A's RMSE is 0.900× B's (95 % CI 0.890–0.910, 8 paired runs): lower
    >>> r.verdict, r.n, round(r.estimate, 2)
    ('lower', 8, 0.9)

    Identical runs give an exact verdict, not a zero-width interval:

    >>> print(compare_runs(b, b.copy(), scale="log_ratio").sentence("A", "B", "RMSE"))
    A's RMSE equals B's in each of the 8 paired runs (to round-off; these runs only, no interval to compute): equal

    The same difference in every run may be chance with few runs (0/1 data); the p-value is
    then the exact sign test's:

    >>> print(compare_runs(np.ones(3), np.zeros(3)).sentence("A", "B", "share lost"))  # doctest: +NORMALIZE_WHITESPACE
    A's share lost minus B's is 1 (the same difference in each of the 3 paired runs, to round-off;
    exact sign test p = 0.25): not resolved by 3 runs (the sign test needs 6 runs of one sign for p < 0.05)

    Four runs cannot resolve a 1 % difference buried in 10 % noise; the sentence says what
    they could have detected:

    >>> d = np.array([0.11, -0.09, 0.1, -0.08])
    >>> print(compare_runs(1.0 + d, np.ones(4)).sentence(unit="m"))  # doctest: +NORMALIZE_WHITESPACE
    A's value minus B's is 0.01 m (95 % CI -0.16 to 0.18 m, 4 paired runs): not resolved by 4 runs
    (80 % power only for differences beyond ±0.23 m)
    """
    a = _per_run(a, "a", scale)
    b = _per_run(b, "b", scale)
    if not isinstance(paired, (bool, np.bool_)):
        raise TypeError(f"paired must be True or False, got {type(paired).__name__}")
    if paired and a.size != b.size:
        raise ValueError(f"a and b must have the same number of runs when paired, got shapes {a.shape} and {b.shape} "
                         "(pass paired=False for independent samples)")
    level = _level(level)
    log = scale == "log_ratio"
    if margin is not None:
        m = _scalar(margin, "margin")
        if not (m > 0 and (m < 1 or not log)):
            raise ValueError(f"margin must be > 0{' and < 1 (a relative margin for a ratio)' if log else ''}, "
                             f"got {margin!r}")
        if level <= 0.5:
            raise ValueError(f"level must be > 0.5 for the equivalence test (TOST uses 1 - 2*(1 - level)), "
                             f"got {level!r}")
        margin = m
    rtol_used = _ROUNDOFF if rtol is None else _rtol(rtol)
    x, y = (np.log(a), np.log(b)) if log else (a, b)
    # per-value round-off scale on the analysis scale (a relative error r of a value is an
    # absolute error r of its logarithm, hence at least 1 for logarithms)
    ux, uy = (np.maximum(np.abs(x), 1.0), np.maximum(np.abs(y), 1.0)) if log else (np.abs(x), np.abs(y))
    if paired:
        d, t = x - y, rtol_used * np.maximum(ux, uy)  # |d_i - d_j| <= t_i + t_j for every pair:
        exact = _common_point(d, t)                  # the intervals d_i ± t_i share a point
        nonzero = int(np.count_nonzero(np.abs(d) > t))  # runs whose difference is not round-off of 0
        zero = exact and nonzero == 0
        n = d.size
        delta, se, df = float(d.mean()), float(d.std(ddof=1) / math.sqrt(n)), float(n - 1)
    else:
        tx, ty = rtol_used * ux, rtol_used * uy
        exact = _common_point(x, tx) and _common_point(y, ty)
        zero = exact and _common_point(np.concatenate([x, y]), np.concatenate([tx, ty]))
        va, vb = float(x.var(ddof=1)) / x.size, float(y.var(ddof=1)) / y.size
        delta, se = float(x.mean() - y.mean()), math.sqrt(va + vb)
        df = (va + vb) ** 2 / (va**2 / (x.size - 1) + vb**2 / (y.size - 1)) if se > 0 else float(x.size + y.size - 2)
    tol = rtol_used * max(float(ux.max()), float(uy.max()))
    if exact:  # no spread beyond round-off: the difference on these runs is known exactly
        se = 0.0
        if zero:
            delta = 0.0
    alpha = 1.0 - level
    tc, tp = stats.t.ppf([1.0 - alpha / 2, _POWER], df).tolist()
    lo, hi = delta - tc * se, delta + tc * se
    mde = (tc + tp) * se
    p_eq = None
    if margin is not None:
        bl, bh = (math.log1p(-margin), math.log1p(margin)) if log else (-margin, margin)
    if se > 0:  # one call: |t| for the two-sided p; the two one-sided TOST statistics
        z = [abs(delta) / se] + ([(delta - bl) / se, (bh - delta) / se] if margin is not None else [])
        sf = stats.t.sf(z, df).tolist()
        p = 2.0 * sf[0]
        if margin is not None:
            p_eq = max(sf[1], sf[2])
    else:  # no spread: exact tests (the sign test paired, the permutation test unpaired)
        inside = margin is not None and bl < delta < bh
        if paired:  # each run's sign is a fair coin under H0: 2 of the 2^n sign patterns are this extreme
            p = 1.0 if zero else min(1.0, math.ldexp(1.0, 1 - nonzero))
            p_one = math.ldexp(1.0, -n)  # one-sided, every run inside the bound
        else:  # one labelling in C(N, n_a) is this extreme, two (mirror) when n_a == n_b
            labellings = math.comb(a.size + b.size, a.size)
            p = 1.0 if zero else min(1.0, (2 if a.size == b.size else 1) / labellings)
            p_one = 1.0 / labellings
        if margin is not None:
            p_eq = p_one if inside else 1.0
    ci = (math.exp(lo), math.exp(hi)) if log else (lo, hi)
    est = math.exp(delta) if log else delta
    return _decide(ComparisonResult(est, ci, se, p, mde, "", delta, df, level, int(a.size), int(b.size), bool(paired),
                                    scale, margin, None, p_eq, 1, p, p_eq, exact, tol,
                                    None if rtol is None else rtol_used))


class HolmResult(NamedTuple):
    """Holm-adjusted p-values (in the order given) and which hypotheses are rejected."""

    p_adjusted: np.ndarray
    reject: np.ndarray


def holm(results, level: float | None = None):
    r"""Holm–Bonferroni step-down control of the family-wise error (Holm 1979).

    With the :math:`m` p-values sorted, :math:`p_{(1)} \le \dots \le p_{(m)}`, the adjusted
    p-values are :math:`\tilde p_{(i)} = \max_{j \le i} \min\{1, (m - j + 1)\,p_{(j)}\}`, and
    :math:`H_{(i)}` is rejected when :math:`\tilde p_{(i)} < \alpha`: the probability of one or
    more false rejections in the family is at most :math:`\alpha` whatever the dependence
    between the tests.

    Parameters
    ----------
    results : a sequence of :class:`ComparisonResult` (all at the same ``level``), or of
        p-values in [0, 1].
    level : confidence level :math:`1 - \alpha`; default the results' level (0.95 for
        p-values). Given with results, it must equal theirs.

    Returns
    -------
    tuple of ComparisonResult or HolmResult
        For results: the same results with ``tests``, ``p_adjusted``,
        ``p_equivalence_adjusted``, ``equivalent`` and ``verdict`` recomputed. The family is
        every test the results perform: one difference test each, plus one TOST for each
        result with a margin (so ``tests`` counts both). The confidence intervals stay at
        ``level``, unadjusted (the sentence reports the adjusted p-value next to them).
        For p-values: :class:`HolmResult` ``(p_adjusted, reject)``, arrays in the order given.

    Examples
    --------
    >>> h = holm([0.01, 0.04, 0.03, 0.005])
    >>> h.p_adjusted.round(3).tolist(), h.reject.tolist()
    ([0.03, 0.06, 0.06, 0.02], [True, False, False, True])
    """
    items = list(results) if isinstance(results, (Sequence, np.ndarray)) and not isinstance(results, str) else None
    if not items:
        raise TypeError(f"results must be a non-empty sequence of ComparisonResult or of p-values, got "
                        f"{type(results).__name__}{' (empty)' if items == [] else ''}")
    if all(isinstance(r, ComparisonResult) for r in items):
        levels = {r.level for r in items}
        if len(levels) != 1 or (level is not None and _level(level) not in levels):
            raise ValueError(f"level must be the same for every result in the family, got results at "
                             f"{sorted(levels)} and level={level!r}")
        lvl = levels.pop()
        ps = [r.p_value for r in items] + [r.p_equivalence for r in items if r.margin is not None]
        adj = _holm_adjust(np.asarray(ps))
        k = len(items)
        eq_adj = iter(adj[k:].tolist())
        return tuple(_decide(dataclasses.replace(r, tests=len(ps), p_adjusted=float(adj[i]),
                                                 p_equivalence_adjusted=next(eq_adj) if r.margin is not None else None))
                     for i, r in enumerate(items))
    if any(isinstance(r, ComparisonResult) for r in items):
        raise TypeError("results must be all ComparisonResult or all p-values, not a mix")
    p = check_finite(as_float_array(items, "results"), "results")
    if p.ndim != 1 or np.any((p < 0) | (p > 1)):
        raise ValueError(f"results must be a 1-D sequence of p-values in [0, 1], got shape {p.shape} "
                         f"with range [{p.min():g}, {p.max():g}]")
    lvl = 0.95 if level is None else _level(level)
    adj = _holm_adjust(p)
    return HolmResult(adj, adj < 1.0 - lvl)


class Sweep(NamedTuple):
    """Comparisons over a parameter range (:func:`compare_sweep`).

    Attributes
    ----------
    values : the parameter values, in the order given.
    results : one :class:`ComparisonResult` per value.
    flips : ``(value_i, value_i+1)`` for each pair of consecutive values whose verdicts differ
        in :attr:`ComparisonResult.kind` (the flip lies between them, at the resolution of the
        grid).
    """

    values: tuple
    results: tuple
    flips: tuple


def compare_sweep(values, fn: Callable[[Any], tuple], *, adjust: str | None = None, **options) -> Sweep:
    """Compare two methods at every value of a parameter and find where the verdict flips.

    Parameters
    ----------
    values : sequence of parameter values (e.g. ``q`` from 0.1 to 100), in sweep order.
    fn : ``fn(value) -> (a, b)``, the per-run values of the two methods at that value (give
        every value the same seed: common random numbers make the sweep smooth).
    adjust : ``None`` (each value at ``level``: enough for "lower at every value tried") or
        ``"holm"`` (the verdicts adjusted over the whole sweep, for claims value by value).
    **options : passed to :func:`compare_runs` (``paired``, ``scale``, ``level``, ``margin``).

    Returns
    -------
    Sweep

    Examples
    --------
    A's advantage grows with the parameter ``s``; 5 runs resolve it from ``s = 0.5`` on:

    >>> import numpy as np
    >>> noise = np.array([0.1, -0.1, 0.05, -0.05, 0.0])
    >>> sw = compare_sweep([0.0, 0.5, 1.0], lambda s: (1.0 - 0.2 * s + noise, np.ones(5)))
    >>> [r.kind for r in sw.results], sw.flips
    (['not resolved', 'lower', 'lower'], ((0.0, 0.5),))
    """
    if not callable(fn):
        raise TypeError(f"fn must be callable(value) -> (a, b), got {type(fn).__name__}")
    if adjust not in (None, "holm"):
        raise ValueError(f"adjust must be None or 'holm', got {adjust!r}")
    vals = tuple(values) if isinstance(values, (Sequence, np.ndarray)) and not isinstance(values, str) else ()
    if not vals:
        raise ValueError(f"values must be a non-empty sequence of parameter values, got {values!r}")
    results = []
    for v in vals:
        pair = fn(v)
        if not (isinstance(pair, tuple) and len(pair) == 2):
            raise TypeError(f"fn must return a pair (a, b) of per-run values, got {type(pair).__name__} "
                            f"for value {v!r}")
        results.append(compare_runs(*pair, **options))
    if adjust == "holm":
        results = holm(results)
    flips = tuple((vals[i], vals[i + 1]) for i in range(len(vals) - 1) if results[i].kind != results[i + 1].kind)
    return Sweep(vals, tuple(results), flips)


# --------------------------------------------------------------------------------------------
# private helpers
# --------------------------------------------------------------------------------------------
def _decide(r: ComparisonResult) -> ComparisonResult:
    """Verdict of ``r`` from its (possibly Holm-adjusted) p-values."""
    alpha = 1.0 - r.level
    equivalent = None if r.margin is None else bool(r.p_equivalence_adjusted < alpha)
    if r.exact and r.delta == 0:  # no difference in any run: a statement about these runs
        verdict = "equal"
    elif r.p_adjusted < alpha:
        verdict = "lower" if r.delta < 0 else "higher"
    elif equivalent:
        verdict = f"equivalent within ±{_margin_text(r.margin, r.scale == 'log_ratio')}"
    else:
        verdict = f"not resolved by {r.n_a if r.paired else f'{r.n_a} + {r.n_b}'} runs"
    return dataclasses.replace(r, verdict=verdict, equivalent=equivalent)


def _common_point(v: np.ndarray, t: np.ndarray) -> bool:
    """Whether every pair satisfies ``|v_i - v_j| <= t_i + t_j``: the intervals ``v_i ± t_i``
    intersect pairwise, which on a line means they share a point (O(n), not O(n^2))."""
    return bool(np.max(v - t) <= np.min(v + t))


def _rtol(value) -> float:
    v = _scalar(value, "rtol")
    if not 0.0 <= v < 1.0:
        raise ValueError(f"rtol must be a relative round-off level in [0, 1), e.g. 1e-9, got {value!r}")
    return v


def _holm_adjust(p: np.ndarray) -> np.ndarray:
    m = p.size
    order = np.argsort(p, kind="stable")
    adj_sorted = np.maximum.accumulate(np.minimum(1.0, (m - np.arange(m)) * p[order]))
    out = np.empty(m)
    out[order] = adj_sorted
    return out


def _per_run(value, name: str, scale: str) -> np.ndarray:
    if scale not in _SCALES:
        raise ValueError(f"scale must be one of {_SCALES}, got {scale!r}")
    arr = check_finite(as_float_array(value, name), name)
    if arr.ndim != 1 or arr.size < 2:
        raise ValueError(f"{name} must be 1-D with one value per run and at least 2 runs, got shape {arr.shape}")
    if scale == "log_ratio" and np.any(arr <= 0):
        raise ValueError(f"{name} must be > 0 for scale='log_ratio' (a ratio of positive values), "
                         f"got minimum {arr.min():g}")
    return arr


def _scalar(value, name: str) -> float:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise TypeError(f"{name} must be a real number, got {type(value).__name__}")
    v = float(value)
    if not math.isfinite(v):
        raise ValueError(f"{name} must be finite, got {value!r}")
    return v


def _level(level) -> float:
    v = _scalar(level, "level")
    if not 0.0 < v < 1.0:
        raise ValueError(f"level must be in (0, 1), e.g. 0.95, got {level!r}")
    return v


def _decimals(se: float) -> int:
    """Decimals that put the last digit at the first significant digit of ``se``."""
    return -math.floor(math.log10(se))


def _round_text(x: float, d: int) -> str:
    return f"{round(x, d) + 0.0:.{max(d, 0)}f}"


def _fmt(x: float, se: float, ref: float | None = None) -> str:
    """``x`` rounded at the first significant digit of ``se``; a bound that would round onto
    the reference ``ref`` (0, or ratio 1) gets up to three more digits, to show its side."""
    if not se > 0:
        return f"{x + 0.0:.6g}"
    d = _decimals(se)
    s = _round_text(x, d)
    for extra in range(1, 4):
        if ref is None or x == ref or float(s) != ref:
            break
        s = _round_text(x, d + extra)
    return s


def _fmt_exact(x: float, tol: float) -> str:
    """``x`` to 6 significant digits, none of them below the round-off bound ``tol``."""
    if tol > 0:
        x = round(x, _decimals(tol) - 1)
    return f"{x + 0.0:.6g}"


def _sig2(x: float) -> str:
    return f"{float(f'{x:.2g}'):g}"


def _fmt_p(p: float) -> str:
    return "< 0.001" if p < 0.001 else f"= {_sig2(p)}"


def _pct(level: float) -> str:
    return f"{100 * level:g} %"


def _margin_text(margin: float, ratio: bool) -> str:
    return f"{100 * margin:g} %" if ratio else f"{margin:g}"
