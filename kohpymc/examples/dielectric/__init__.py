r"""A stand-in for the dielectric-charging example of the paper (Section 6.2, Table 3).

The paper calibrates a compact dielectric-charging model of an RF-MEMS switch (its
Ref. [31]) against transient currents measured on a 200 nm Si₃N₄ film at 12
combinations of voltage V and temperature T, 0–100 s.  Neither that model nor the data
are public, so this module builds a documented stand-in from the same physical
ingredients and the same seven parameters with the priors of Table 3; the hidden
truth adds a mechanism the stand-in lacks, so that a model discrepancy exists.

Inputs ``V`` (applied voltage, V), ``T`` (temperature, K), ``t`` (time, s, in
[0, 100]); output ``J``, the external current density in **nA/cm²** (1 nA/cm² =
1e-5 A/m²).  At the true parameters the 12 design settings span about 3–350 nA/cm².

Physics
-------
SI units; ``q``, ``h``, ``m0``, ``ε0``, ``k`` are taken from ``scipy.constants``.
Parameters: ``ln_NT`` (ln N_T, trap density in m⁻³), ``phi_B`` (Φ_B, injection barrier,
eV), ``ln_sigma`` (ln σ, capture cross-section in m²), ``ln_gamma`` (ln γ, FP attempt
frequency in 1/s), ``eps_inf`` (ε_∞), ``m_eff`` (m*/m0), ``E_A`` (trap activation
energy, eV).  Film ``d = 200 nm``, static ``ε_r = 7.5``.

* **Fowler–Nordheim injection** at the cathode, field ``E`` (V/m)::

      J_FN(E) = A E² exp(-B / E),   A = q³ m0 / (8π h m* (qΦ_B)),
                                    B = 8π √(2 m*) (qΦ_B)^{3/2} / (3 q h)

  with ``m* = m_eff · m0``, i.e. ``A ≈ 1.54e-6 / (m_eff Φ_B)`` A/V² and
  ``B ≈ 6.83e9 √m_eff Φ_B^{3/2}`` V/m for Φ_B in volts.
* **Trapping.**  Electrons drift across the film at ``v_d = μ E_app`` (``E_app =
  V/d``, fixed hopping mobility ``μ = 1e-7`` m²/Vs) and are captured at the rate
  ``σ v_th (N_T - n_t)`` per electron (``v_th = 1e5`` m/s): the probability that an
  injected electron is captured in one transit is
  ``P_c(n_t) = 1 - exp(-σ (N_T - n_t) v_th d / v_d)``, which reduces to
  ``σ (N_T - n_t) · (v_th / v_d) · d`` when small — the capture rate
  ``∝ σ (J_FN / q)(N_T - n_t)`` of the compact model, kept below one electron per
  injected electron.  Without the ``v_th / v_d`` enhancement the Table 3 range of
  ``σ N_T d`` (≤ 0.011) would trap too little charge to change the current in 100 s.
* **Frenkel–Poole emission** of trapped electrons at the applied field::

      e(V, T) = γ / (1 + exp(x)),   x = q (E_A - β √E_app) / (k T),   β = √(q / (π ε0 ε_∞))

  i.e. the textbook ``γ exp(-x)`` whenever the lowered barrier is positive (x ≫ 1,
  relative difference ``e^{-x}``), saturating smoothly at the attempt frequency γ
  where the Poole lowering would exceed ``E_A`` (otherwise the rate, and the stiffness
  of the equation below, would overflow at small ε_∞).
* **Trapped charge** ``n_t(t)`` (m⁻³), taken uniform across the film, starting empty::

      dn_t/dt = f(n_t) = J_FN(E_inj) P_c(n_t) / (q d) - e n_t

  and it lowers the injecting field: for a uniform charge the centroid is at ``d/2``,
  so ``E_inj = V/d - q n_t d / (2 ε0 ε_r)``.  The field at the centroid (used for
  the emission) stays ``V/d``.
* **External current** (Ramo–Shockley: at fixed V the external current is the
  conduction current averaged over the film; the electron flux falls by the net
  trapping between the cathode and x)::

      J(t) = J_FN(E_inj) - (q d / 2) dn_t/dt

  which tends to the injection current at steady state.

The transient is field-feedback-limited injection: trapped charge screens the cathode,
so the current falls roughly like 1/t toward the emission-limited steady state
``J_ss = q d e n_ss / P_c``, which rises with T (thermally activated emission).  At the
true parameters every setting decays visibly over 0–100 s.  Over the Table 3 box the
behaviour ranges from no current (large barrier, heavy mass) to instant quasi-
equilibrium (at the prior centre ``E_A ≈ 0.5`` eV, γ ≈ 1e9/s emit in microseconds);
a visible transient needs emission slower than ~1/s, i.e. ``E_A`` in the upper part
of its range and γ in the lower part (about 1 % of (θ, setting) pairs drawn from the
box, none from its central half).  The output over the box spans ~1e-17 to 1e9
nA/cm², so start a sampler near the data (e.g. at a least-squares fit), not at the
centre of the box, where the trap parameters change the output by ~1e-8 relative.

Numerics
--------
The equation is a scalar autonomous ODE with ``f`` strictly decreasing, so it is
solved semi-analytically per (V, T) setting: the steady state ``n_ss`` (root of f,
safeguarded Newton in ``ln n``, converged to machine precision), then the exact
``t(n) = ∫ dn / f(n)`` by quadrature on a fixed grid ``n = n_ss · expit(s)``,
``s ∈ [-10, 18]`` (1121 nodes, step 0.025, Euler–Maclaurin-corrected trapezoid, fourth
order), and ``n(t)`` by cubic Hermite interpolation of ``s(t)`` with the exact slopes
``1 / (dt/ds)``.  Below the first node (``n < 4.5e-5 n_ss``) ``t`` is the trapezoid in n
from 0 and ``n(t)`` a Hermite cubic from ``n(0) = 0``,
after the last (``n_ss - n < 2e-8 n_ss``) the exact linear relaxation
``n_ss - n ∝ exp(f'(n_ss) t)``.  There is no adaptive step, so the output is a smooth,
deterministic function of θ (central finite differences at relative steps 6e-6 and
1e-4 agree); it agrees with ``solve_ivp(method="Radau", rtol=1e-10)`` to ~1e-6
relative.  Rows are grouped by their (V, T) setting (any values, any t ≥ 0); the steady
state, the quadrature, the interpolation and the sensitivity integrals below are
numba-compiled loops (``kernels``; numba comes with PyTensor) over the settings, each
solved independently of the others and only as far along its grid as its latest row
needs (the nodes computed are a prefix of the whole grid's, so the result is the same).

Hidden truth: dipolar polarization
----------------------------------
The truth adds what the stand-in lacks, the orientation polarization of dipoles in the
nitride (a known second charging mechanism of SiN MEMS dielectrics).  After the voltage
step the polarization ``P(t) = ε0 Δε E_app (1 - exp(-t/τ))`` relaxes with a thermally
activated Debye time ``τ(T) = τ_300 exp(E_pol/k (1/T - 1/300 K))`` and adds the
displacement current::

    J_pol(t) = ε0 Δε (V/d) / τ(T) · exp(-t / τ(T))

with ``Δε = 3``, ``τ_300 = 30`` s, ``E_pol = 0.155`` eV (τ ≈ 30 s at 300 K, 7.5 s at
390 K): a positive discrepancy (53 nA/cm² at t = 0 for 30 V, 390 K; 38 at the first
measured time; RMS 5.9 over the design) that decays in time (so the time-decaying
variance of Eq. 14 suits it), grows with V and whose size and decay rate depend on T.
It cannot be absorbed by θ: the least-squares fit of the stand-in to the noiseless
truth (from the true θ) leaves an RMS residual of 2.6 nA/cm², about 9 × the noise sd.

Data follow the paper: 3 voltages (20, 25, 30 V, i.e. 1–1.5 MV/cm; the paper's
Fig. 8 shows 20 V, 360 K) × 4 temperatures (300, 330, 360, 390 K), 40 equally spaced
times ``t_k = 2.5 k`` s (k = 1..40), odd-indexed times for calibration, even-indexed
for validation.  The paper's noise variance
depends on (V, T) (Eq. 28); :class:`~kohpymc.data.CalibrationData` carries one σ_obs, so
the noise here is one known sd, ``NOISE_SD = 0.3`` nA/cm², for every setting.

Sampling
--------
Start chains at :func:`least_squares_fit` (multi-start, does not use the truth).
Gradients are exact by default (``physics_model()``, :func:`charging_current_sensitivities`):
for the autonomous scalar equation, differentiating ``t = ∫_0^n dn'/f(n'; θ)`` at fixed
t gives ``∂n/∂θ = f(n) ∫_0^n f_θ/f² dn'``, integrated on the solution's own grid
(``f_θ`` combines five functions of n, so four integrals per setting suffice), with the
steady-state limit ``-f_θ/f_n`` beyond the last node; the current follows by the chain
rule.  They agree with central differences of the model to ≤ 2e-4 (column norms, at the
truth, the fit, near the truth and at prior draws) and with differences on a 4× finer
grid to ≤ 3e-5 — closer to the exact derivative than differencing the discretised model
(~8e-5), and exact at sub-second times where forward differences are off by up to 20 %.
The gradient reuses the solution of the value call at the same point, so a sampler's
value plus gradient costs ~2 model runs: 0.56 ms on the 240 calibration rows, and one
log density plus gradient of M0 0.65 ms, 3.4–3.7× less than with the earlier numpy
loops (2.2–2.4 ms; interleaved runs on the shared 2-core machine at load ~6, best of
300 evaluations; medians 0.7 against 6.5–8.5 ms).  Finite differences remain available
(``physics_model("central")``, ``physics_model("forward", vectorized=True)``).

The posterior is hard for NUTS even so.  The current fixes the Fowler–Nordheim exponent
``B ∝ √m* Φ_B^{3/2}`` to ~1e-4 but barely sees the prefactor, so ``(Φ_B, m*)`` lie on a
thin curved ridge (condition number ~9e3 of the column-scaled sensitivities at the
fit); the Taylor check at the fit is full rank and names it as a practical
non-identifiability, ``the data inform mostly phi_B·m_eff^0.347 ≈ (phi_B^3·m_eff)^(1/3)``
(i.e. B², see :meth:`kohpymc.identifiability.IdentifiabilityReport.weakly_informed`).
Without a discrepancy (M0) the posterior piles against the ``Φ_B`` upper and ``ln γ``
lower bounds, which the Laplace whitening cannot make Gaussian (score 27 against 1.125
for a Gaussian): NUTS needs ~60 leapfrog steps per draw there, so 4 × 2000 iterations
take far longer than the issue's 20-minute budget for six formulations (see
``docs/paper-reproduction.md`` for the measured numbers).

Layout
------
``constants`` (units, Table 3 box, truth, design settings), ``emission`` (Fowler–Nordheim,
Frenkel–Poole), ``kinetics`` (the trapped-charge equation and its solution), ``current``
(stand-in current, batch, Jacobian; the hidden truth), ``fit`` (the
:class:`~kohpymc.PhysicsModel` and its least-squares fit), ``data`` (design, synthetic data,
split), ``formulations`` (Eq. 29, M0–M5) and ``kernels`` (the compiled loops of the
solution).  Everything public is importable from here.
"""

from kohpymc.examples.dielectric.constants import (
    CURRENT_UNIT,
    DELTA_EPS,
    E_POL,
    EPS_R,
    MOBILITY,
    NOISE_SD,
    PRIOR_RANGES,
    T_END,
    TAU_300,
    TEMPERATURES,
    THERMAL_VELOCITY,
    THICKNESS,
    TRUE_PARAMS,
    VOLTAGES,
)
from kohpymc.examples.dielectric.current import (
    charging_current,
    charging_current_batch,
    charging_current_jacobian,
    charging_current_sensitivities,
    polarization_current,
    true_current,
)
from kohpymc.examples.dielectric.data import design, generate_data, split_calibration_validation
from kohpymc.examples.dielectric.emission import fowler_nordheim, frenkel_poole_rate
from kohpymc.examples.dielectric.fit import least_squares_fit, physics_model
from kohpymc.examples.dielectric.formulations import eq29_log_variance, eq29_mean, formulations
from kohpymc.examples.dielectric.kinetics import trapped_charge

__all__ = [
    "THICKNESS",
    "EPS_R",
    "MOBILITY",
    "THERMAL_VELOCITY",
    "CURRENT_UNIT",
    "PRIOR_RANGES",
    "TRUE_PARAMS",
    "VOLTAGES",
    "TEMPERATURES",
    "T_END",
    "NOISE_SD",
    "DELTA_EPS",
    "TAU_300",
    "E_POL",
    "fowler_nordheim",
    "frenkel_poole_rate",
    "trapped_charge",
    "charging_current",
    "charging_current_batch",
    "charging_current_jacobian",
    "charging_current_sensitivities",
    "polarization_current",
    "true_current",
    "physics_model",
    "design",
    "generate_data",
    "split_calibration_validation",
    "least_squares_fit",
    "eq29_mean",
    "eq29_log_variance",
    "formulations",
]
