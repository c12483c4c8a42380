"""
Billings' residual correlation tests for nonlinear model validity.

Billings (Nonlinear System Identification, 2013, ch. 5; Billings & Voon 1986) calls a model
adequate when its residuals ε hold nothing that the input u or the residuals themselves could still
predict:

    φεε(τ)      = δ(τ)           ε(k) vs ε(k-τ)                     tested on τ = 1..L
    φuε(τ)      = 0              u(k-τ) vs ε(k)                      tested on τ = -L..L, τ != 0
    φu²'ε(τ)    = 0              u²'(k-τ) vs ε(k)                    tested on τ = -L..L, τ != 0
    φu²'ε²'(τ)  = 0              u²'(k-τ) vs ε²'(k)                  tested on τ = -L..L, τ != 0
    φε(εu)(τ)   = 0              ε(k) vs (εu)(k-τ)                   tested on τ = 1..L

with x' = x - mean(x). Billings writes the last test as E[ε(t) ε(t-1-τ) u(t-1-τ)], τ >= 0; our lag
τ = 1 is his τ = 0. Each φ is a normalised cross-correlation (means removed, divided by the root of
the product of the two energies), so it lies in [-1, 1], and for N samples of independent sequences
it is approximately normal with standard deviation 1/√N: the 95 % band is ±1.96/√N.

Lag 0 is not tested (DESIGN.md): φεε(0) = 1 by definition, and a one-step predictor that uses u(k)
makes φuε(0) ≈ 0 by least squares, so lag 0 carries no evidence.

Pass rule. By default a test passes when at most floor(0.05 x tested lags) lags leave the 95 %
band (the rate expected by chance) and none leaves the 99.9 % band ±3.29/√N, so one large
correlation (a clearly missing term) still fails. Why not strict (every lag inside, DESIGN.md's
first wording): for truly white residuals each lag leaves the band with probability 0.05, so a test
over L = 20 lags passes with probability 0.95**20 = 0.36 and, measured, 0 of 200 white residual
sequences passed all five strict tests at N = 25,000. `max_outside_fraction=0` restores strict.
See docs/validation.md.

All correlations are computed with FFTs (scipy.fft, one transform per sequence), O(N log N).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import fft as sp_fft

from piezo_narx_ros.errors import DataError

# Names used in metrics.json, `piezo-narx evaluate` output and figure titles, in Billings' order.
TEST_NAMES = ('phi_ee', 'phi_ue', 'phi_u2e', 'phi_u2e2', 'phi_e_eu')
TEST_LABELS = {
    'phi_ee': r'$\phi_{\varepsilon\varepsilon}(\tau)$',
    'phi_ue': r'$\phi_{u\varepsilon}(\tau)$',
    'phi_u2e': r'$\phi_{u^{2\prime}\varepsilon}(\tau)$',
    'phi_u2e2': r'$\phi_{u^{2\prime}\varepsilon^{2}}(\tau)$',
    'phi_e_eu': r'$\phi_{\varepsilon(\varepsilon u)}(\tau)$',
}
_TWO_SIDED = {'phi_ue', 'phi_u2e', 'phi_u2e2'}


@dataclass
class CorrelationTest:
    """One test: φ(τ) for every lag, which lags are tested, and the verdict."""

    name: str
    lags: np.ndarray        # (M,) integer lags in samples, including 0 for reference
    values: np.ndarray      # (M,) normalised correlation in [-1, 1]; NaN when undefined
    n_tested: int           # number of lags != 0 that count
    n_outside: int          # tested lags outside the band
    passed: bool

    def to_dict(self) -> dict:
        """JSON-ready form (lists of numbers)."""
        return {'lags': self.lags.tolist(),
                'values': [None if not np.isfinite(v) else float(v) for v in self.values],
                'n_tested': self.n_tested, 'n_outside': self.n_outside, 'passed': self.passed}


@dataclass
class CorrelationResult:
    """The five tests on one residual sequence."""

    n: int                   # number of residual samples used
    band: float              # half-width of the 95 % band, 1.96/sqrt(n)
    hard_band: float         # with a tolerance, no lag may exceed this (99.9 %, 3.29/sqrt(n))
    max_lag: int
    max_outside_fraction: float
    tests: dict[str, CorrelationTest] = field(default_factory=dict)
    # Several channels: the (output, input) indices whose residual and input these tests judged.
    pair: dict | None = None

    @property
    def passed(self) -> bool:
        """Return True when all five tests pass."""
        return all(t.passed for t in self.tests.values())

    def verdicts(self) -> dict[str, bool]:
        """{test name: passed} for the five tests."""
        return {name: t.passed for name, t in self.tests.items()}

    def to_dict(self, with_values: bool = True) -> dict:
        """JSON-ready form; `with_values=False` keeps only the verdicts and counts."""
        tests = {}
        for name, t in self.tests.items():
            d = t.to_dict()
            if not with_values:
                d.pop('lags')
                d.pop('values')
            tests[name] = d
        return {'n': self.n, 'band': self.band, 'hard_band': self.hard_band,
                'max_lag': self.max_lag,
                'max_outside_fraction': self.max_outside_fraction, 'passed': self.passed,
                'tests': tests, **({'pair': self.pair} if self.pair is not None else {})}


def _spectrum(x: np.ndarray, n_fft: int) -> tuple[np.ndarray, float]:
    """(rfft of x minus its mean, energy of x minus its mean)."""
    x = x - x.mean()
    # np.sum, not np.dot: a threaded BLAS dot stalls on a busy machine for no gain at this size.
    return sp_fft.rfft(x, n_fft), float(np.sum(x * x))


def _correlate(spec_a, spec_b, lags: np.ndarray, n_fft: int) -> np.ndarray:
    (fa, ea), (fb, eb) = spec_a, spec_b
    den = np.sqrt(ea * eb)
    if den == 0.0 or not np.isfinite(den):
        return np.full(lags.size, np.nan)
    # irfft(conj(A) B)[τ mod n] = Σk a(k-τ) b(k); n >= N + L keeps |τ| <= L free of wrap-around.
    full = sp_fft.irfft(np.conj(fa) * fb, n_fft)
    return full[lags % n_fft] / den


def cross_correlation(a, b, max_lag: int) -> tuple[np.ndarray, np.ndarray]:
    """
    Normalised cross-correlation φab(τ) = Σk a'(k-τ) b'(k) / sqrt(Σa'² Σb'²), τ = -L..L.

    a' and b' are a and b with their means removed. Returns (lags (2L+1,), values (2L+1,)); the
    values are NaN when either sequence is constant (the correlation is undefined).
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    n_fft = sp_fft.next_fast_len(a.size + int(max_lag), real=True)
    lags = np.arange(-max_lag, max_lag + 1)
    return lags, _correlate(_spectrum(a, n_fft), _spectrum(b, n_fft), lags, n_fft)


def correlation_tests(residuals, u, max_lag: int = 20,
                      max_outside_fraction: float = 0.05) -> CorrelationResult:
    """
    Run the five Billings tests on residuals ε (m) against input u (V), equal-length 1-D arrays.

    `max_lag` (samples, >= 1) is L; `max_outside_fraction` in [0, 1) is the fraction of tested
    lags allowed outside ±1.96/sqrt(N) (0 = strict: every lag inside; > 0: none beyond
    ±3.29/sqrt(N) either). A test whose correlation is undefined (constant input or residual) does
    not pass.
    """
    e = np.asarray(residuals, dtype=np.float64)
    u = np.asarray(u, dtype=np.float64)
    if e.ndim != 1 or e.shape != u.shape:
        raise DataError(f'correlation tests need residuals and input of equal 1-D shape, got '
                        f'{e.shape} and {u.shape}')
    if not (np.all(np.isfinite(e)) and np.all(np.isfinite(u))):
        raise DataError('correlation tests: residuals or input contain NaN or inf')
    max_lag = int(max_lag)
    if max_lag < 1:
        raise DataError(f'correlation tests: max_lag must be >= 1, got {max_lag}')
    if e.size < 4 * max_lag:
        raise DataError(f'correlation tests: {e.size} residual samples are too few for '
                        f'max_lag={max_lag} (need >= {4 * max_lag})')
    if not 0.0 <= max_outside_fraction < 1.0:
        raise DataError(f'correlation tests: max_outside_fraction must be in [0, 1), got '
                        f'{max_outside_fraction}')
    n = e.size
    band = 1.96 / np.sqrt(n)
    # Strict: the 95 % band is the only limit. Tolerant: the 99.9 % band is a hard limit.
    hard_band = 3.29 / np.sqrt(n) if max_outside_fraction > 0 else band
    u2 = u * u - np.mean(u * u)
    e2 = e * e - np.mean(e * e)
    n_fft = sp_fft.next_fast_len(n + max_lag, real=True)
    spectra = {'e': _spectrum(e, n_fft), 'u': _spectrum(u, n_fft), 'u2': _spectrum(u2, n_fft),
               'e2': _spectrum(e2, n_fft), 'eu': _spectrum(e * u, n_fft)}
    pairs = {  # name -> (sequence lagged by τ, sequence at k)
        'phi_ee': ('e', 'e'),
        'phi_ue': ('u', 'e'),
        'phi_u2e': ('u2', 'e'),
        'phi_u2e2': ('u2', 'e2'),
        'phi_e_eu': ('eu', 'e'),   # ε(k) against (εu)(k-τ)
    }
    all_lags = np.arange(-max_lag, max_lag + 1)
    result = CorrelationResult(n=n, band=float(band), hard_band=float(hard_band), max_lag=max_lag,
                               max_outside_fraction=float(max_outside_fraction))
    for name in TEST_NAMES:
        lagged, current = pairs[name]
        lags = all_lags
        values = _correlate(spectra[lagged], spectra[current], lags, n_fft)
        if name not in _TWO_SIDED:
            keep = lags >= 0
            lags, values = lags[keep], values[keep]
        tested = lags != 0
        n_tested = int(tested.sum())
        if np.any(np.isnan(values[tested])):
            n_outside, passed = n_tested, False
        else:
            magnitude = np.abs(values[tested])
            n_outside = int(np.sum(magnitude > band))
            passed = (n_outside <= int(np.floor(max_outside_fraction * n_tested))
                      and not np.any(magnitude > hard_band))
        result.tests[name] = CorrelationTest(name=name, lags=lags, values=values,
                                             n_tested=n_tested, n_outside=n_outside,
                                             passed=bool(passed))
    return result
