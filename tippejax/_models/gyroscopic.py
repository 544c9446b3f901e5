r"""The gyroscopic level: a slow flow for $\theta$ alone, with the nutation averaged out.

The model is the paper's SO(3) approximation (Sec. 2.2: translation dropped in the friction law,
the same as the `so3` and `routhian` levels), reduced once more. Symbols as in the paper and
`docs/notes.md` (Conventions): $x = \cos\theta$, $h = R - \epsilon x$, $\Omega = \dot\varphi$ (precession rate),
$n = \dot\psi + \dot\varphi\cos\theta$ (spin), $J$ the Jellet (eq. jello),
$D = R^2A\sin^2\theta + C(Rx-\epsilon)^2$.

**Assumptions.**

1. $J$ is fixed. This is not an approximation: $J$ is exactly conserved by the full model
   (eqs. Jellet, jello), whatever the friction law.
2. The slow manifold: $\dot\theta$ is of the order of the friction ($\mu$), so the inertia of the
   slow motion ($M_\theta\ddot\theta$, $\tfrac12 M_\theta'\dot\theta^2$) and the friction term
   $\mu R'_n h^2\dot\theta$ of the $\theta$-equation are dropped (they are $O(\mu^2)$). What
   remains of the $\theta$-equation of $L'$ (the first of eqs. reducedeqs, in Euler angles) is
   $\partial L'/\partial\theta = 0$ at $\dot\theta = 0$:

   $$\sin\theta\,\big(A\Omega^2\cos\theta - C n\Omega - m g\epsilon\big) = 0. \tag{G1}$$

   This is the gyroscopic balance: the gyroscopic torque
   $\Omega\sin\theta\,(Cn - A\Omega\cos\theta)$ balances the torque of the normal force about
   the centre of mass, $R_n\,\epsilon\sin\theta$.
   On (G1) eq. reactie gives exactly $R'_n = m g$ (at $\dot\theta = 0$); the flow uses $R_n = mg$.
3. Eliminating $n$ with eq. jello, (G1) becomes a quadratic for the precession rate:

   $$A h\,\Omega^2 - J\,\Omega - m g\epsilon\,(R\cos\theta - \epsilon) = 0,\qquad
     \Delta = J^2 + 4 A h\, m g\epsilon\,(R\cos\theta - \epsilon). \tag{G2}$$

   and then $n = (A\Omega^2\cos\theta - m g\epsilon)/(C\Omega)$.

**Which root.** The level follows the root of larger $|\Omega|$,
$\Omega = (J + \mathrm{sgn}(J)\sqrt\Delta)/(2Ah) \approx J/(Ah) \approx Cn/(A\cos\theta)$: the
precession at about the nutation frequency, with the angular momentum nearly vertical
($L_{\rm hor} \propto Cn - A\Omega\cos\theta = -mg\epsilon/\Omega \to 0$). It is the slow
manifold because it is the one the motion settles on: linearised at a pole in a regular chart
(the SO(3) model), the two complex modes of the top are the two roots of (G2) (frequencies
$\Omega_\pm$), and the one on this root grows or decays at the rate of this flow (standard
top, $n_0 = 60$ rad/s: $0.760 + 71.3i$ against $0.764$ here), while the other root's mode (the
classical slow precession, $\Omega \approx -mg\epsilon(R-\epsilon)/J$) decays about five times
faster ($-4.77 - 4.64i$): that mode is the "nutation" a launch with $\omega = n a$ sheds in the
first half second (`docs/notes.md`, Launches and the slow manifold). Along the small root the slip is large ($p \approx
Rn$) and the motion leaves it. Where relative equilibria lie on the small root (tops with
$A/C < (1 + \epsilon/R)/2$, near $\theta = \pi$), this level does not follow them (see below).

**The slip and the friction torque.** With $\dot\theta$ slow the slip velocity of $Q$ is
$\sin\theta\, p$ across the vertical plane $\Pi$ plus $h\dot\theta$ in it, with

$$p = R\dot\psi + \epsilon\dot\varphi = R n - \Omega(R\cos\theta - \epsilon) = \dot{\bar\varphi}.$$

The $\psi$-equation of $L'$ with the force $Q'$ (Sec. 2.2; equivalently eq. reducedeqs2, since
$Cn = R\,\partial\mathcal R/\partial\dot{\bar\varphi} - \epsilon J/S$) is exact:
$\tfrac{d}{dt}(Cn) = Q'_\psi = -\mu R'_n R\sin^2\theta\, p$. On the slow manifold
$n = n(\theta; J)$, so $\dot\theta = \dot n/(dn/d\theta)$, and with $F_\Omega = 2Ah\Omega - J$
($= \pm\sqrt\Delta$) and $dn/dx$ from implicit differentiation of (G2),

$$\dot\theta = \frac{\mu m g R\,\sin\theta\; p\, F_\Omega}
{A\Omega F_\Omega + \epsilon(A\Omega^2 + m g R)\,(A\cos\theta + m g\epsilon/\Omega^2)}. \tag{G3}$$

Every term is a smooth function of $x = \cos\theta$ and $\dot\theta \propto \sin\theta$: the flow
is regular at $\theta = 0, \pi$, which are fixed points (a vertical launch stays vertical).

**Fixed points and stability.** Besides the poles, $\dot\theta = 0$ where $p = 0$: rolling
without slipping, which on (G1) is $W'(\theta) = 0$ (eq. crit_amendedpot) -- the intermediate
states of eq. define_intstates. At such a state the slope of (G3) is
$-\mu m g\sin^2\theta\, W''/(\beta'^2 + M_{\bar\varphi}W'')$, and the denominator is
$M_\theta M_{\bar\varphi}\nu^2 > 0$ with $\nu$ the nutation frequency below: stable exactly where
$W'' > 0$ (eq. stabilityba). At the poles the slope changes sign where $W''$ does, at $J_1$,
$J_2$ (eqs. n1, n2), wherever the relative equilibria branching off there lie on this root:
always at $\theta = 0$, and at $\theta = \pi$ if $A/C > (1 + \epsilon/R)/2$. Otherwise (as in
Group IIa near $\theta = \pi$) the other root carries the change of stability: there the
nutation about this root grows ($\sigma > 0$ below), which the level watches and reports.

**Large spin.** As $J \to \infty$, (G3) tends to
$\dot\theta = (\mu m g R^2/A)\,(1 - \tfrac{\epsilon}{R}\cos\theta)\sin\theta\,
\big((\tfrac AC - 1)\cos\theta + \tfrac\epsilon R\big)$: the rise rate does not depend on the
spin, and its sign is that of eq. Exist (Groups I, II, III).

**Comparison with the literature.** Moffatt, Shimomura & Branicki (2004) (gyroscopic
approximation, to leading order in the spin) and Ueda, Sasaki & Watanabe (2005) (the gyroscopic
balance condition, GBC, $A\Omega\cos\theta = Cn$: $L$ vertical) balance the gyroscopic torque
alone. (G1) keeps the torque of the normal force, $mg\epsilon\sin\theta$; the GBC is its
$J \to \infty$ limit. This changes three things. The fixed points of (G3) are the intermediate
states of eq. define_intstates at every $J$ (with the GBC only the limit above, whose zeros are
$0, \pi, \theta_c$); their stability is the $W''$ verdict at every $J$, not only a linearisation
about the steady states (as the paper says of USW, Sec. 6); and (G2) can have no real root:
$\Delta < 0$, which at $\theta = \pi$ is the sleeping-top condition $|n_\pi| < n_* =
2\sqrt{Amg\epsilon}/C$ (Sec. 4). USW use a modified Coulomb friction; here it is eq. viscfric.

**The nutation it drops.** About the slow manifold the top nutates at frequency $\nu$,
$\nu^2 = ((Cn - 2A\Omega\cos\theta)^2 + A^2\Omega^2\sin^2\theta)/(A M_\theta) > 0$
($M_\theta = A + m\epsilon^2\sin^2\theta$; $U''/M_\theta$ of the heavy top at fixed momenta). Its
amplitude $a$ (in $\theta$) changes at the rate $\sigma$, found by averaging the reduced system
(eqs. reducedeqs, reducedeqs2) linearised about the slow manifold over a period: with
$K = \partial_p(\tfrac12 M_{\bar\varphi}'p^2 + \beta'p) = M_{\bar\varphi}'p + \beta'$, the momentum
$q = \delta(M_{\bar\varphi}\dot{\bar\varphi} + \beta)$ is driven by the nutation as
$\dot q = \alpha\,\delta\theta + \dots$ with

$$\alpha = \mu\sin^2\theta\,(R'_n + p\,\partial_p R'_n)\frac{K}{M_{\bar\varphi}}
 - \mu p\,\partial_\theta(R'_n\sin^2\theta),$$

and feeds back as the force $(K/M_{\bar\varphi})q$, a damping
$c_q = K\alpha/(M_{\bar\varphi}\nu^2)$. Hence

$$\sigma = -\frac{\mu R'_n h^2 + c_q}{2M_\theta} - \frac12\frac{d\ln(M_\theta\nu)}{dt}$$

(the last term: the adiabatic invariant of the oscillator). Every term is regular at the poles,
where $\sigma$ is the growth rate of the other root's mode; at the relative equilibria it is the
real part of the nutation pair of the paper's characteristic polynomial. $\sigma$ is negative
for slow spins but turns positive during the rise at fast ones (standard top: for
$n_0 \gtrsim 140$ rad/s; $\sigma \approx +9$/s at $\theta = 1.2$ for $n_0 = 200$): the slow
manifold then repels and the nutation, first damped, grows again -- the route to the contact
loss of `docs/notes.md`, Contact loss. The level carries $\ln a$ ($\dot{\ln a} = \sigma$, from the launch's own
nutation, see below) so that it can say when the dropped nutation has become large.

**The level's coordinate.** The level integrates $u = \ln\tan(\theta/2)$ (the Mercator
coordinate of the axis), not $\theta$: $\dot u = \dot\theta/\sin\theta$ is the `rate` of (G3),
regular, and nearly constant near the poles, where $\theta$ itself grows or decays
exponentially; the steps then follow only the turn of the top (54 Dopri5 steps for a 20 s
inverting run, against 118 in $\theta$). $\cos\theta = -\tanh u$, $\sin\theta = 1/\cosh u$, so
no trigonometric function is evaluated along the run. A pole itself is $|u| \geq$ `POLE`,
where $\theta$ is exactly $0$ or $\pi$ and $u$ does not move (a vertical launch stays
vertical). The step size is controlled on $u$: an absolute error in $u$ is a relative error in
$\tan(\theta/2)$.

**Where the level ends** (`Conditions.chart`; the run continues in the full model from the
state on the slow manifold, reported as `sol.model == "gyroscopic->full"`, and a launch outside
the chart is integrated by the full model from the start):

- $\Delta/(J^2 + 4Ahmg\epsilon|R\cos\theta - \epsilon|) <$ `BALANCE_MARGIN`: no (or barely a)
  real root of (G2): the spin is too slow for gyroscopic balance at this $\theta$ (near the fold
  $\Delta = 0$ the two roots merge and (G3) is not Lipschitz);
- $\sigma > 0$: the slow manifold repels and the nutation grows (at fast spins during the rise).
  This is the route to the full model's contact loss, which the slow flow ($R_n = mg$) cannot
  see, so the full model takes over where the nutation starts to grow, before $R_n$ can come
  near zero. It restarts from the state on the slow manifold, without the (by then tiny) residue
  of the launch's nutation: its own nutation grows from its own small departure from the slow
  manifold, and its contact loss comes later than from the launch itself (standard top,
  $\theta_0 = 0.1$: 5.72 s against 5.03 s at 225 rad/s, 5.65 s against 4.81 s at 300 rad/s);
- the nutation exceeds `NUTATION_LAUNCH_MAX` (in practice only at launch): the launch is too far
  from the slow manifold for its projection.

`GyroscopicLevel(hand_over=False)` is the slow flow alone, as before: it stops at the chart end
with `RESULTS.no_gyroscopic_balance` (the $\sigma > 0$ condition then reads: the nutation is
larger than `NUTATION_MAX` and growing). `GyroscopicLevel(stop_at_hand_over=True)` stops where
the run would hand over, for a caller that continues it itself: the outcome maps of
`model="auto"` (`tippejax/_map_stages.py`), which also give the level the nutation the full
model carries (`GyroscopicLevelState.nutation_rate`, `contact_margin`). That nutation is not
the one this level's $\sigma$ describes: in the full model, the other root's mode splits at
the vertical state into one that decays faster than $\sigma$ and one in which the centre of
mass rolls round with the contact point and which barely decays (`pole_linearisation` in
`full.py`; standard top at 200 rad/s: $-0.06$/s against $\sigma = -5.1$/s). A launch at
$\theta_0 = 0.1$ keeps about 0.035 rad of it through the rise; that is why the full model
restarted from the slow manifold at the hand-over loses contact later than from the launch
(above).

**Projection of a launch** (`from_state`; the option `projection`). A launch with
$\omega = n a$ is not on the slow manifold (`docs/notes.md`, Launches and the slow manifold):
the slow flow must start from the launch's slow-mode content, not its $\theta$. Near a pole
both modes are linear: in complex notation $\xi = a_X + i a_Y$, $w = \omega_X + i\omega_Y$,
every state has $w = r\xi$ with $r = \dot\psi + i\dot\theta/\sin\theta$, and each mode has the
$r$ of its root: $r_+$ this root's, $r_-$ the other root's.

*Linear projection* (`project_launch`, `projection="linear"`). The slow component
$\xi_s = (w - r_-\xi)/(r_+ - r_-)$, with $r_-$ at the nearer pole and $r_+$ at the launch's
$\theta$, and $\sin\theta_s = |\xi_s|$; the nutation is the rest, $a_0 = |\xi - \xi_s|$ (at least
`NUTATION_FLOOR`). It is exact on the slow manifold (`to_state` then `from_state` returns
$\theta$, and $a_0 = 0$) and, near a pole, the exact linear projection. For $\omega = n a$ the
slow component is small, $\theta_s \approx \theta_0|n - r_-|/|r_+ - r_-| \propto \theta_0/n$
($|n - r_-|$ is of the order of the friction rate), while the launch's nutation (the other
root's mode) has the amplitude $\vartheta_0 \approx \theta_0$. Two effects of that finite
amplitude are not small against $\theta_s$, and the $t_{\rm invert}$ error grows with the
spin (standard top, $\theta_0 = 0.1$: $+0.13\%$, $-0.31\%$, $-1.6\%$, $-3.4\%$ against SO(3)
at $n_0 = 100, 150, 225, 300$ rad/s): the other root's spin at fixed $J$ depends on the tilt,
$n_- \approx J/(C(R\cos\vartheta - \epsilon))$, so its $r_-$ at the pole is off by
$\approx n\vartheta_0^2 R/(2(R - \epsilon))$ from the launch's own; and what the nutation feeds
into the slow mode while it decays (below).

*Averaged projection* (`average_launch`, `projection="averaged"`, the default): first-order
averaging over the nutation, in closed form. The derivation:

1. *Two time scales.* A launch with $\omega \approx n a$ is mostly the other root's mode: $L$
   along $a$, tilted by $\vartheta$, precessing slowly ($\Omega_- = O(1/n)$) and decaying at a
   rate of the order of the friction along that root's own slow flow (G3)
   (`slow_manifold(branch=-1)`: $\dot\vartheta_-$). The slow component is a small nutation
   about that state (amplitude $O(\vartheta/n)$), of frequency $\nu_- \approx Cn/A$: "The
   nutation it drops" with the two roots exchanged. Averaged over its phase with the other
   root's state frozen (first order in $1/n$: the state moves by $O(\dot\vartheta_-/\nu_-)$
   in a period), its amplitude $a$ (in $\theta$) grows at the rate $\sigma_-(\vartheta)$, the
   $\sigma$ of that section on the other root. (The SO(3) vector field linearised at the
   other root's state changes its real part with $\vartheta$ as $\sigma_-$ does, growing as
   $n^2$; the difference does not grow with the spin, e.g. 0.04/s at $\vartheta = 0.1$ for
   group III, and against the SO(3) transient $\sigma_-$ does the better:
   `tests/test_projection.py`.)
2. *At the pole the roots exchange their roles exactly*: $\sigma_-(0) = \dot u_+(0)$, the slow
   flow's rate; $\dot u_-(0) = \sigma_+(0)$; $\mathrm{sgn}(J)\,\nu_-(0) + \Omega_-(0) =
   \Omega_+(0)$ (sympy, `tests/test_projection.py`, with $J$ and $g$ written through the two
   roots of (G2)). Once the nutation has decayed, the slow component is the slow manifold
   near the pole and grows at the slow flow's rate.
3. *The near-identity transformation.* With

   $$I(\vartheta) = \int_0^{\vartheta}\frac{\sigma_-(\vartheta') - \sigma_-(0)}
     {|\dot\vartheta_-(\vartheta')|}\,d\vartheta',$$

   the coordinate $\ln a + I(\vartheta)$ moves at exactly the slow flow's rate along the
   averaged motion, $\frac{d}{dt}(\ln a + I) = \sigma_- - (\sigma_- - \sigma_-(0)) =
   \dot u_+(0)$, and is $\ln\sin\theta$ on the slow manifold ($\vartheta = 0$): it labels the
   fibre through the launch, to first order. Hence

   $$\ln\sin\theta_s = \ln a_0 + I(\vartheta_c), \tag{P}$$

   with $a_0$ the launch's slow content and $\vartheta_c$ the tilt (from the pole) of the
   centre of its nutation, from which the nutation decays.
4. *The launch's slow content* $a_0$ and $\vartheta_c$: the other root's state at the
   launch's tilt $\vartheta_0$ (same $J$), linearised conservatively in the reduced chart ("The
   nutation it drops": the momentum $q = M_{\bar\varphi}\delta p$ shifts the nutation's centre
   by $Kq/(M_{\bar\varphi}M_\theta\nu^2)$),
   $a_0^2 = (\delta\theta - K\delta p/(M_\theta\nu_-^2))^2 + (\delta\dot\theta/\nu_-)^2$ and
   $\vartheta_c = \vartheta_0 \pm K\delta p/(M_\theta\nu_-^2)$, with $\delta$ the launch minus
   that state and $p$ the slip. For $\omega = n a$ the shift is $O(\vartheta_0/n^2)$; with
   $\dot\theta$, $\dot\varphi$ at launch it is first order (standard top, $\theta_0 = 0.15$,
   250 rad/s, $\dot\theta_0 = -2$, $\dot\varphi_0 = 10$ rad/s: $\ln\theta_s$ 0.006 off the
   SO(3) transient's, 0.032 with $I$ taken from $\vartheta_0$). The phase ($\varphi_s$) is that
   of the split with the other root's mode frozen at the launch's tilt,
   $\xi_s = (w - r_-(\vartheta_0)\xi)/(r_+ - r_-(\vartheta_0))$, turned by
   $\Phi = \int(\mathrm{sgn}(J)(\nu_- - \nu_-(0)) + \Omega_- - \Omega_-(0))\,dt$ over the
   decay, and the body's angle about the vertical ($\varphi \pm \psi$) by $\Psi$
   (`launch_transient`). The reduced chart is singular at the pole, so where the slow
   component is not small against the nutation the split is used: $\ln\sin\theta_s$ is the
   mean of (P) and $\ln|\xi_s|$ with the weights $|\xi - \xi_s|^2$ and $|\xi_s|^2$. The split
   is exact on either root (a state on the slow manifold projects onto itself); for
   $\omega = n a$ the weight of (P) is within $10^{-3}$ of 1. A launch that mixes comparable
   amounts of both modes is the least well served (on the slow manifold at $\theta = 0.05$,
   150 rad/s, with 8 rad/s added to $\omega_X$: 0.012 in $\ln\theta_s$, as the linear
   projection; the fibre projection 0.0001).
5. *Leading order* (sympy): $\sigma_-(\vartheta) = \sigma_-(0) + \gamma_2\vartheta^2 +
   O(\vartheta^4)$ with $\gamma_2 \to -\mu m\epsilon R(R - \epsilon)\Omega_+^2/(2C)$ and
   $|\dot\vartheta_-| \to \mu mgR(R - \epsilon)\vartheta/C$ as $J \to \infty$, so

   $$I(\vartheta_0) \approx -\frac{\epsilon\,\Omega_+^2\vartheta_0^2}{4g},\qquad
     \Omega_+ \approx \frac{Cn}{A},$$

   independent of $\mu$. $\gamma_2$ comes from the dependence of $R'_n$ on the slip (the
   vertical acceleration $\epsilon\sin^2\theta\,\Omega(\Omega\cos\theta - Cn/A)$ of the
   centre of mass in eq. reactie): the nutation modulates $R_n$ at its own frequency, and the
   friction on the decaying mode's large slip ($p \approx Rn$) under that modulated $R_n$ is
   a torque that damps the slow mode for as long as the decaying mode lasts. The linear
   projection is $I = 0$ with $r_-$ at the pole. Standard top, $\vartheta_0 = 0.1$:
   $I = -0.024$, $-0.21$ at $n_0 = 100$, 300 rad/s (leading form $-0.025$, $-0.21$); at
   $\vartheta_0 = 0.2$, 300 rad/s, $-0.82$ (leading form $-0.85$). The level evaluates the
   integrals by Gauss-Legendre quadrature of their first-order integrands (`AVERAGING_NODES`);
   no solve.

It is first order in $1/n$ and neglects: the motion of the other root's state within a
nutation period beyond the adiabatic term of $\sigma_-$; the difference between (G3) on the
other root and that mode's true decay (0.04% at the pole); and terms nonlinear in the slow
component (its ratio to the nutation is $O(1/n)$ for $\omega = n a$). Against the slow state
the SO(3) transient leaves, $\ln\theta_s$ is off by at most 0.0045 for $\omega = n a$
launches of three groups at $\theta_0 \leq 0.2$, 150-300 rad/s (`tests/test_projection.py`;
the linear projection: 0.07 to 1.7). It needs the other root's mode to decay all the way
from the launch's tilt to the pole (else the linear projection is used). Standard top, $\omega = n a$, $\theta_0 = 0.1$, $t_{\rm invert}$
of the slow flow against SO(3): $-0.27\%$, $-0.11\%$, $-0.04\%$, $-0.02\%$ at
$n_0 = 100, 150, 225, 300$ rad/s ($|{\rm error}| \sim n_0^{-2.6}$ over 100-300 rad/s). Most of
it is the slow flow's own error: launched from the slow state the SO(3) transient really
leaves (followed for 1 s and 1.5 s, projected there, the slow flow run back, extrapolated to
zero settle time) the slow flow is off by $-0.29\%$, $-0.12\%$, $-0.04\%$, $-0.01\%$
($n_0^{-3.0}$). The averaged projection's own part is $+0.025\%$ at 100 rad/s, $+0.009\%$ at
150 and within $\pm 0.006\%$ from 175 to 300 (about $n_0^{-1.9}$); the fibre projection's is
$+0.012\%$ at 100 rad/s and grows to $-0.034\%$ at 300. For groups III and IIa and at
$\theta_0 = 0.05$ the averaged projection's own error is the smaller at almost every spin;
at $\theta_0 = 0.2$ above 100 rad/s the fibre projection's is ($-0.001\%$ to $-0.029\%$
against $-0.024\%$ to $-0.049\%$). See `benchmarks/LEVELS.md`.
Its cost is that of the linear projection and a few evaluations of (G3) and $\sigma$.

*Fibre projection* (`settle_launch`, `projection="fibre"`; Fenichel's fast fibres of the slow
manifold, numerically): the launch is followed in the SO(3) model for the time `settle_time`
its nutation takes to decay to `SETTLE_AMPLITUDE` (at the other root's rate at the pole, at
most `SETTLE_TIME_MAX`; about 0.4 s for $\theta_0 = 0.1$), where the linear projection is
accurate (its error is quadratic in the remaining amplitude), and the slow flow is integrated
back from there to the launch time. $t_{\rm invert}$ as above: $-0.28\%$, $-0.11\%$,
$-0.05\%$, $-0.04\%$. The cost is one short SO(3) solve and one short slow solve (both at rtol
`SETTLE_RTOL`) per launch, about 250 times the averaged projection's in a batch of 256
launches; a launch with $a_0 <$ `SETTLE_AMPLITUDE` skips them.

**What is dropped.** The nutation (and with it any contact loss it causes: $R_n = mg$ on the
slow manifold), and the translation of the centre of mass (position and velocity are reported
as zero, as by the SO(3) and Routhian levels).

**Accuracy** (standard top, against the SO(3) model, rtol $10^{-8}$). Launched on the slow
manifold at $\theta = 0.02$: $|\Delta t_{\rm invert}| = 0.064, 0.013, 0.0019$ s at
$n_0 = 50, 100, 200$ rad/s (about $n_0^{-2.5}$). Launched with $\omega = n a$ at
$\theta_0 = 0.1$ (averaged projection): $-0.27\%, -0.11\%, -0.04\%, -0.02\%$ at
$n_0 = 100, 150, 225, 300$, mostly the slow flow's own error (above; the full model differs
from SO(3) by $+0.3\%$ and $+1.0\%$ at 100 and 150 rad/s, and loses contact before inverting
at 225 and 300). About 55 slow steps for a 20 s run, against about 1400-2000 steps for the
full model at $n_0 = 100$ (`benchmarks/LEVELS.md`; the ratio moves with the machine's load).

**Not for:** the nutation, the translation, or the moment of a contact loss (where the manifold
repels the run is the full model's, see above); launches with more nutation than
`NUTATION_LAUNCH_MAX` (the full model takes them from the start); slow spins (it is an
expansion in $1/J$); tops with $A/C < (1 + \epsilon/R)/2$ near $\theta = \pi$ (Group IIa),
whose relative equilibria there lie on the other root (the nutation grows and the full model
takes over); and $\mu = 0$ ($\theta$ is then constant on the slow manifold and the nutation never
decays).
"""

from __future__ import annotations

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._invariants import jellet
from .._state import State, euler_angles, euler_rates, state_from_euler
from .._top import TippeTop
from .base import AbstractLevel, Conditions
from .full import FullLevel
from .so3 import SO3Level

BALANCE_MARGIN = 0.01
r"""The level stops where $\Delta/(J^2 + 4Ahmg\epsilon|R\cos\theta - \epsilon|)$ falls below
this."""

NUTATION_MAX = 0.05
r"""The level stops where the nutation amplitude it drops exceeds this (rad) while growing."""

NUTATION_LAUNCH_MAX = 0.25
r"""A launch with more nutation than this (rad) is refused: its projection is not trusted."""

NUTATION_FLOOR = 1e-12
r"""Nutation amplitude (rad) given to a launch that has none (on the slow manifold)."""

HAND_OVER_MARGIN = 0.0
r"""With `hand_over`, the level hands over to the full model where $-\sigma/\nu$ falls below
this: where the nutation about the slow manifold stops decaying fast."""

SETTLE_AMPLITUDE = 0.01
r"""The launch's nutation is followed in the SO(3) model until its linear projection's amplitude
is about this (rad); see "Projection of a launch"."""

SETTLE_TIME_MAX = 1.0
r"""The longest the launch transient is followed in the SO(3) model (s)."""

SETTLE_RTOL, SETTLE_ATOL = 1e-7, 1e-10
r"""Tolerances of the two short solves of the fibre projection."""

AVERAGING_NODES = 6
r"""Gauss-Legendre nodes of the averaged projection's integrals over the decay of a launch's
nutation ($I$, $\Phi$, $\Psi$ of "Projection of a launch"). The integrands are smooth and
nearly linear in the tilt: for the standard top 4 nodes agree with 32 to $10^{-6}$ up to a tilt
of 0.25."""

POLE = 750.0
r"""$|u| \geq$ `POLE` ($u = \ln\tan(\theta/2)$) is a pole: $e^{-|u|}$ is then exactly zero (in
float32 and float64), $\theta$ is exactly $0$ or $\pi$, and $u$ does not move."""


def _sign(J):
    return jnp.where(J >= 0, 1.0, -1.0).astype(jnp.result_type(J))


def _safe_sqrt(x):
    """sqrt(x) for x > 0, else 0, with a finite derivative everywhere."""
    positive = x > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, x, 1.0)), 0.0)


def _safe_log(x, floor):
    """log(x) for x > 0, else `floor`, with a finite derivative everywhere."""
    positive = x > 0
    return jnp.where(positive, jnp.log(jnp.where(positive, x, 1.0)), floor)


def cos_sin(u) -> tuple[Array, Array]:
    r"""$(\cos\theta, \sin\theta) = (-\tanh u, 1/\cosh u)$ for $u = \ln\tan(\theta/2)$; exact
    (and with finite derivatives) at the poles $|u| \geq$ `POLE`."""
    e = jnp.exp(-jnp.abs(u))
    return -jnp.tanh(u), 2 * e / (1 + e * e)


def theta_of(u) -> Array:
    r"""$\theta = 2\arctan e^u$ of $u = \ln\tan(\theta/2)$."""
    x, s = cos_sin(u)
    return jnp.arctan2(s, x)


def log_tan_half(theta) -> Array:
    r"""$u = \ln\tan(\theta/2)$, clipped to $[-$`POLE`$, $`POLE`$]$ (the poles)."""
    theta = jnp.asarray(theta, dtype=jnp.result_type(theta, float))
    x, s = jnp.cos(theta), jnp.abs(jnp.sin(theta))
    north = x >= 0
    # tan(theta/2) = s/(1 + x) = (1 - x)/s: the form without cancellation on each side
    tangent = jnp.where(north, s / (1 + x), s / (1 - x))
    u = _safe_log(tangent, -POLE)
    return jnp.clip(jnp.where(north, u, -u), -POLE, POLE)


def balance_discriminant(top: TippeTop, x, J) -> Array:
    r"""$\Delta = J^2 + 4Ah\,mg\epsilon(Rx - \epsilon)$ of (G2), $x = \cos\theta$; $< 0$: no
    balance."""
    h = top.R - top.eps * x
    return J**2 + 4 * top.A * h * top.m * top.g * top.eps * (top.R * x - top.eps)


def precession_rate(top: TippeTop, x, J, *, branch: int = 1) -> Array:
    r"""A root $\Omega$ of (G2) at $x = \cos\theta$.

    `branch=1` (the slow manifold): $(J + \mathrm{sgn}(J)\sqrt\Delta)/(2Ah)$;
    `branch=-1` (the classical slow precession): $-2mg\epsilon(Rx - \epsilon)/(J + \mathrm{sgn}(J)
    \sqrt\Delta)$, the same root written without cancellation. $\sqrt\Delta$ is taken as 0 where
    $\Delta < 0$.
    """
    h = top.R - top.eps * x
    root = _sign(J) * _safe_sqrt(balance_discriminant(top, x, J))
    if branch == 1:
        return (J + root) / (2 * top.A * h)
    if branch == -1:
        return -2 * top.m * top.g * top.eps * (top.R * x - top.eps) / (J + root)
    raise ValueError(f"branch must be 1 or -1, got {branch!r}.")


class SlowManifold(eqx.Module):
    r"""The slow manifold at one $\theta$ for one $J$ (see the module docstring).

    - `precession`: $\Omega = \dot\varphi$, a root of (G2).
    - `spin`: $n = (A\Omega^2\cos\theta - mg\epsilon)/(C\Omega)$.
    - `slip`: $p = Rn - \Omega(R\cos\theta - \epsilon)$ (slip across $\Pi$ is $p\sin\theta$).
    - `rate`: $\dot\theta/\sin\theta$ of (G3) (regular at the poles; $= \dot u$).
    - `theta_dot`: $\dot\theta$ of (G3).
    - `discriminant`: $\Delta$ of (G2).
    """

    precession: Array
    spin: Array
    slip: Array
    rate: Array
    theta_dot: Array
    discriminant: Array


def _slow_manifold(top: TippeTop, x, s, J, branch: int = 1) -> SlowManifold:
    """`slow_manifold` at $x = \\cos\\theta$, $s = \\sin\\theta$ (the level's own evaluations)."""
    m, g, eps, R, A, C = top.m, top.g, top.eps, top.R, top.A, top.C
    weight = m * g * eps  # m g eps
    h = R - eps * x
    lever = R * x - eps
    discriminant = J**2 + 4 * A * h * weight * lever
    root = _sign(J) * _safe_sqrt(discriminant)
    if branch == 1:
        omega = (J + root) / (2 * A * h)
    elif branch == -1:
        omega = -2 * weight * lever / (J + root)
    else:
        raise ValueError(f"branch must be 1 or -1, got {branch!r}.")
    spin = (A * omega**2 * x - weight) / (C * omega)
    slip = R * spin - omega * lever
    f_omega = 2 * A * h * omega - J
    denominator = A * omega * f_omega + eps * (A * omega**2 + m * g * R) * (
        A * x + weight / omega**2
    )
    rate = top.mu * m * g * R * slip * f_omega / denominator
    return SlowManifold(
        precession=omega,
        spin=spin,
        slip=slip,
        rate=rate,
        theta_dot=rate * s,
        discriminant=discriminant,
    )


def slow_manifold(top: TippeTop, theta, J, *, branch: int = 1) -> SlowManifold:
    r"""Precession, spin, slip and the slow flow (G3) at $\theta$ on one root of (G2).

    `branch=1` is the level's slow manifold; `branch=-1` (the other root) is singular at
    $\cos\theta = \epsilon/R$ and serves the projection at the poles and the analysis.
    """
    theta = jnp.asarray(theta, dtype=jnp.result_type(theta, top.m))
    return _slow_manifold(top, jnp.cos(theta), jnp.sin(theta), J, branch)


def gyroscopic_theta_dot(top: TippeTop, theta, J) -> Array:
    r"""$\dot\theta$ of the slow flow (G3) on the level's root of (G2)."""
    return slow_manifold(top, theta, J).theta_dot


def limit_theta_dot(top: TippeTop, theta) -> Array:
    r"""The $J \to \infty$ limit of (G3): $(\mu mgR^2/A)(1 - \tfrac\epsilon R\cos\theta)
    \sin\theta\,((\tfrac AC - 1)\cos\theta + \tfrac\epsilon R)$."""
    x, s = jnp.cos(theta), jnp.sin(theta)
    a, e = top.A / top.C, top.eps / top.R
    return top.mu * top.m * top.g * top.R**2 / top.A * (1 - e * x) * s * ((a - 1) * x + e)


class Nutation(eqx.Module):
    r"""The nutation about the slow manifold at one $\theta$: `frequency_squared` $\nu^2$ and
    `damping` $\sigma$ (see the module docstring)."""

    frequency_squared: Array
    damping: Array


def _nutation(top: TippeTop, x, s, J, sm: SlowManifold) -> Nutation:
    r"""$\nu^2$ and $\sigma$ at $x = \cos\theta$, $s = \sin\theta$, in closed form.

    The derivatives in $x$ (at fixed $\dot{\bar\varphi} = p$, and along the manifold) are
    written out; `tests/test_gyroscopic.py` checks them against autodiff of the definitions.
    """
    m, g, eps, R, A, C, mu = top.m, top.g, top.eps, top.R, top.A, top.C, top.mu
    weight = m * g * eps
    omega, n, p = sm.precession, sm.spin, sm.slip
    s2 = s * s
    big_s = eps**2 + R**2
    lever = R * x - eps
    h = R - eps * x
    # D, kappa (eq. routh1) and their x-derivatives
    d = R**2 * A * s2 + C * lever**2
    d_x = -2 * R**2 * A * x + 2 * C * R * lever
    kappa = R * A * eps * s2 + C * lever * (R + eps * x)
    kappa_x = -2 * R * A * eps * x + C * (R**2 - eps**2 + 2 * R * eps * x)
    # R'_n at rest as a function of (x, p) with phi_dot, n from eq. routh1:
    # R'_n = m N / Q, N = g + eps s^2 w (w x - C n/A), Q = 1 + m eps^2 s^2/A
    c_dot = R * omega - eps * (n - omega * x)  # the cyclic rate, c = R phi - eps psi
    gyro = omega * x - C * n / A
    q = 1 + m * eps**2 * s2 / A
    numerator = g + eps * s2 * omega * gyro
    rn = m * numerator / q  # = m g on the manifold
    w_p = (eps - R * kappa / d) / big_s
    n_p = (R + eps * kappa / d) / big_s + w_p * x
    rn_p = m * eps * s2 * (w_p * gyro + omega * (w_p * x - C * n_p / A)) / q
    c_x = -(kappa_x * p + c_dot * d_x) / d
    w_x = R * c_x / big_s
    n_x = -eps * c_x / big_s + w_x * x + omega
    numerator_x = eps * (-2 * x * omega * gyro
                         + s2 * (w_x * gyro + omega * (w_x * x + omega - C * n_x / A)))
    q_x = -2 * x * m * eps**2 / A
    rn_x = m * (numerator_x * q - numerator * q_x) / q**2
    # M_phibar / sin^2 = A C / D, and B_p / sin(theta) = -(dM_phibar/dx p + dbeta/dx)
    inertia_phibar = A * C / d
    dm_x = A * C * (-2 * x * d - s2 * d_x) / d**2
    dbeta_x = J / big_s * (kappa_x * d - kappa * d_x) / d**2
    coupling = -(dm_x * p + dbeta_x)
    inertia = A + m * eps**2 * s2  # M_theta
    # nu^2 = P/(A M_theta), P = (C n - 2 A Omega x)^2 + A^2 Omega^2 sin^2, along the manifold
    omega_x = (weight * R + A * eps * omega**2) / (2 * A * h * omega - J)  # from (G2)
    n_x_manifold = A / C * (omega + x * omega_x) + weight * omega_x / (C * omega**2)
    lead = C * n - 2 * A * omega * x
    lead_x = C * n_x_manifold - 2 * A * (omega + x * omega_x)
    big_p = lead**2 + (A * omega) ** 2 * s2
    big_p_x = 2 * lead * lead_x + A**2 * (2 * omega * omega_x * s2 - 2 * x * omega**2)
    nu2 = big_p / (A * inertia)
    inertia_x = -2 * x * m * eps**2
    log_m_nu_x = 0.5 * (inertia_x / inertia + big_p_x / big_p)  # d ln(M_theta nu)/dx
    drive = (mu * (rn + p * rn_p) * coupling / inertia_phibar + mu * s2 * p * rn_x
             - 2 * mu * p * rn * x)  # alpha / sin(theta)
    friction = -(mu * rn * h**2 + coupling * drive / (inertia_phibar * nu2)) / (2 * inertia)
    adiabatic = 0.5 * sm.rate * s2 * log_m_nu_x  # -(1/2) d ln(M_theta nu)/dt
    return Nutation(frequency_squared=nu2, damping=friction + adiabatic)


def _momentum_coupling(top: TippeTop, x, s, J, p) -> Array:
    r"""$K/\sin\theta$, $K = \partial_\theta(M_{\bar\varphi}p + \beta)$ at fixed $p$: the force
    $(K/M_{\bar\varphi})\,q$ with which the momentum $q$ drives the nutation (see "The
    nutation it drops"; as in `_nutation`)."""
    eps, R, A, C = top.eps, top.R, top.A, top.C
    big_s = eps**2 + R**2
    lever = R * x - eps
    d = R**2 * A * s * s + C * lever**2
    d_x = -2 * R**2 * A * x + 2 * C * R * lever
    kappa = R * A * eps * s * s + C * lever * (R + eps * x)
    kappa_x = -2 * R * A * eps * x + C * (R**2 - eps**2 + 2 * R * eps * x)
    dm_x = A * C * (-2 * x * d - s * s * d_x) / d**2
    dbeta_x = J / big_s * (kappa_x * d - kappa * d_x) / d**2
    return -(dm_x * p + dbeta_x)


def nutation_frequency(top: TippeTop, theta, J, *, branch: int = 1) -> Array:
    r"""$\nu$ of the nutation about the slow manifold:
    $\nu^2 = ((Cn - 2A\Omega\cos\theta)^2 + A^2\Omega^2\sin^2\theta)/(A M_\theta)$.

    `branch=-1`: about the other root of (G2) ($\nu_-$ of "Projection of a launch")."""
    theta = jnp.asarray(theta, dtype=jnp.result_type(theta, top.m))
    x, s = jnp.cos(theta), jnp.sin(theta)
    sm = _slow_manifold(top, x, s, J, branch)
    return jnp.sqrt(_nutation(top, x, s, J, sm).frequency_squared)


def nutation_damping(top: TippeTop, theta, J, *, branch: int = 1) -> Array:
    r"""$\sigma$: growth rate of the amplitude of the nutation about the slow manifold (negative:
    it decays), averaged over a nutation period. See the module docstring.

    `branch=-1`: about the other root of (G2) ($\sigma_-$ of "Projection of a launch": the
    growth rate of a launch's slow component while its nutation decays)."""
    theta = jnp.asarray(theta, dtype=jnp.result_type(theta, top.m))
    x, s = jnp.cos(theta), jnp.sin(theta)
    return _nutation(top, x, s, J, _slow_manifold(top, x, s, J, branch)).damping


def _contact_proximity(top: TippeTop, s, log_amplitude, nutation: Nutation, fraction):
    r"""$\ln(f g) - \ln(\epsilon\sin\theta\,a\nu^2)$: positive while the nutation of
    amplitude $a = e^{\ln a}$ takes less than the fraction $f$ of $g$ off the normal force."""
    lift = top.eps * s * nutation.frequency_squared
    return jnp.log(fraction * top.g) - _safe_log(lift, -2 * POLE) - log_amplitude


def _validity(top: TippeTop, x, J, log_amplitude, nutation: Nutation, *,
              hand_over: bool = False, margin: float = HAND_OVER_MARGIN, sin_theta=None,
              contact_margin: float | None = None) -> Array:
    h = top.R - top.eps * x
    lever = top.R * x - top.eps
    weight = top.m * top.g * top.eps
    scale = J**2 + 4 * top.A * h * weight * jnp.abs(lever)
    balance = (J**2 + 4 * top.A * h * weight * lever) / scale - BALANCE_MARGIN
    decaying = -nutation.damping / jnp.sqrt(nutation.frequency_squared)
    small = jnp.log(NUTATION_MAX) - log_amplitude
    projectable = jnp.log(NUTATION_LAUNCH_MAX) - log_amplitude
    if hand_over:
        # hand over to the full model as soon as the slow manifold repels: the full model then
        # grows its own nutation (and finds its own contact loss) from the slow state
        chart = jnp.minimum(jnp.minimum(balance, decaying - margin), projectable)
        if contact_margin is not None:
            proximity = _contact_proximity(top, sin_theta, log_amplitude, nutation,
                                           contact_margin)
            chart = jnp.minimum(chart, proximity)
        return chart
    return jnp.minimum(jnp.minimum(balance, jnp.maximum(small, decaying)), projectable)


def validity(top: TippeTop, theta, J, log_amplitude) -> Array:
    r"""`Conditions.chart` of the level: $\min(\Delta_{\rm rel} - $ `BALANCE_MARGIN`$,
    \max(\ln(a_{\max}/a), -\sigma/\nu), \ln(a_{\rm launch}/a))$, with $\ln a$ = `log_amplitude`.

    Positive where (G2) has a real root with margin and the nutation is small or decaying; the
    level stops where it falls through zero (see the module docstring).
    """
    theta = jnp.asarray(theta, dtype=jnp.result_type(theta, top.m))
    x, s = jnp.cos(theta), jnp.sin(theta)
    nutation = _nutation(top, x, s, J, _slow_manifold(top, x, s, J))
    return _validity(top, x, J, log_amplitude, nutation)


def entry_margin(top: TippeTop, theta, J, log_amplitude, *, nutation_max, decay_min,
                 balance_min, contact_max) -> Array:
    r"""How far inside the level's chart the slow state at `theta` (Jellet `J`) with a
    nutation of amplitude $e^{\ln a}$ (`log_amplitude`) is, with margins:
    $\min(\Delta_{\rm rel} -$ `BALANCE_MARGIN` $-$ `balance_min`, $-\sigma/\nu -$
    `decay_min`, $\ln$ `nutation_max` $- \ln a$, $\ln$(`contact_max` $g) -
    \ln(\epsilon\sin\theta\,a\nu^2))$ (see `contact_margin` of `GyroscopicLevel`). Positive: the level may take over a run of
    the full model there (`outcome_map(model="auto")`, `tippejax/_map_stages.py`). The margins
    above those at which the level hands over (`BALANCE_MARGIN`, `HAND_OVER_MARGIN`) keep a run
    from handing back and forth."""
    theta = jnp.asarray(theta, dtype=jnp.result_type(theta, top.m))
    x, s = jnp.cos(theta), jnp.sin(theta)
    sm = _slow_manifold(top, x, s, J)
    nutation = _nutation(top, x, s, J, sm)
    h = top.R - top.eps * x
    lever = top.R * x - top.eps
    weight = top.m * top.g * top.eps
    scale = J**2 + 4 * top.A * h * weight * jnp.abs(lever)
    balance = (J**2 + 4 * top.A * h * weight * lever) / scale - BALANCE_MARGIN
    frequency = _safe_sqrt(nutation.frequency_squared)
    decaying = -nutation.damping / jnp.where(frequency > 0, frequency, 1.0)
    small = jnp.log(nutation_max) - log_amplitude
    margin = jnp.minimum(jnp.minimum(balance - balance_min, decaying - decay_min), small)
    margin = jnp.minimum(margin, _contact_proximity(top, s, log_amplitude, nutation, contact_max))
    return jnp.where(jnp.isfinite(margin), margin, -1.0)


def _complex_ratio(top, theta, J, branch):
    """(Re, Im) of r = psi_dot + i theta_dot/sin(theta) of a mode (see the module docstring)."""
    sm = slow_manifold(top, theta, J, branch=branch)
    return sm.spin - sm.precession * jnp.cos(theta), sm.rate


def _split(top: TippeTop, state: State, J, theta_in):
    """(Re, Im) of xi_s = (w - r_in xi)/(r_out - r_in), r_in of the other root at `theta_in`,
    r_out of the level's root at the state's own tilt (complex arithmetic in real components)."""
    theta, _, _ = euler_angles(state)
    a, w = state.axis, state.omega
    in_re, in_im = _complex_ratio(top, theta_in, J, -1)
    out_re, out_im = _complex_ratio(top, theta, J, 1)
    num_re = w[0] - (in_re * a[0] - in_im * a[1])
    num_im = w[1] - (in_re * a[1] + in_im * a[0])
    den_re, den_im = out_re - in_re, out_im - in_im
    den2 = den_re**2 + den_im**2
    den2 = jnp.where(den2 > 0, den2, 1.0)
    c_re = (num_re * den_re + num_im * den_im) / den2
    c_im = (num_im * den_re - num_re * den_im) / den2
    return c_re, c_im


def _slow_state(state: State, north, c_re, c_im, log_gain, turn, spin_turn, side):
    """(u, phi_s, psi_s, ln a0) of the slow component xi_s = c of a state: its modulus scaled by
    e^{log_gain}, its phase advanced by `turn`, and the body's angle about the vertical
    (phi + side psi) turned by `spin_turn` (all 0 and side = 1 for the linear projection)."""
    _, phi, psi = euler_angles(state)
    a = state.axis
    mod2 = c_re**2 + c_im**2
    positive = mod2 > 0
    modulus = jnp.where(positive, jnp.sqrt(jnp.where(positive, mod2, 1.0)), 0.0)
    modulus = jnp.clip(modulus * jnp.exp(log_gain), 0, 1)
    # sin(tilt) = |xi_s|; tan(tilt/2) = sin/(1 + cos), no cancellation
    # (no infinite rate where the modulus is clipped at 1: the event watch of
    # `FullUntilSlowLevel` differentiates this along the full model)
    log_tan = _safe_log(modulus / (1 + _safe_sqrt(1 - modulus**2)), -POLE)
    u = jnp.clip(jnp.where(north, log_tan, -log_tan), -POLE, POLE)
    # xi_s = -i sin(theta_s) e^{i phi_s}: phi_s = atan2(Re xi_s, -Im xi_s)
    phi_s = jnp.where(positive, jnp.arctan2(c_re, -c_im) + turn, phi)
    psi_s = psi + side * (phi - phi_s + spin_turn)
    # the nutation: what is left of the horizontal axis, xi - xi_s
    rest2 = (a[0] - c_re) ** 2 + (a[1] - c_im) ** 2
    floor2 = jnp.asarray(NUTATION_FLOOR, rest2.dtype) ** 2
    log_amplitude = 0.5 * jnp.log(jnp.maximum(rest2, floor2))
    return u, phi_s, psi_s, log_amplitude


def _projection(top: TippeTop, state: State):
    """(u, phi_s, psi_s, ln a0, J) of `project_launch`, u = ln tan(theta_s/2)."""
    J = jellet(top, state)
    theta, _, _ = euler_angles(state)
    north = state.axis[2] >= 0
    pole = jnp.where(north, 0.0, jnp.pi).astype(theta.dtype)
    c_re, c_im = _split(top, state, J, pole)
    zero = jnp.zeros_like(c_re)
    # the linear projection keeps phi + psi (at both poles)
    return (*_slow_state(state, north, c_re, c_im, zero, zero, zero, 1.0), J)


def project_launch(top: TippeTop, state: State):
    r"""$(\theta_s, \varphi_s, \psi_s, \ln a_0, J)$: a (single) state projected onto the slow
    manifold, with the amplitude $a_0$ of its nutation.

    See "Projection of a launch" in the module docstring. Regular at the poles.
    """
    u, phi_s, psi_s, log_amplitude, J = _projection(top, state)
    return theta_of(u), phi_s, psi_s, log_amplitude, J


class GyroscopicLevelState(eqx.Module):
    r"""State of the gyroscopic level: $u = \ln\tan(\theta/2)$, the precession and spin angles,
    the log of the nutation amplitude, and $J$.

    Only $u$ is dynamic: $\dot u = \dot\theta/\sin\theta$, the `rate` of (G3), regular and
    nearly constant near the poles, where $\theta$ itself grows or decays exponentially (see
    "The level's coordinate" in the module docstring). $\varphi$ and $\psi$ are integrated from
    $\dot\varphi = \Omega$ and $\dot\psi = n - \Omega\cos\theta$ to report the orientation, and
    `nutation` $= \ln a$ from $\sigma$ to watch the nutation that is dropped; none of them feeds
    back. $J$ is constant. `nutation_rate` (None by default): a constant $\dot{\ln a}$ that
    replaces $\sigma$, for a run whose nutation is not the SO(3) model's (the full model's
    rolling mode, `tippejax/_map_stages.py`).
    """

    log_tan_half_theta: Float[Array, ""]
    phi: Float[Array, ""]
    psi: Float[Array, ""]
    nutation: Float[Array, ""]
    jellet: Float[Array, ""]
    nutation_rate: Float[Array, ""] | None = None

    @property
    def theta(self) -> Array:
        return theta_of(self.log_tan_half_theta)

    @classmethod
    def from_theta(cls, theta, phi, psi, nutation, jellet) -> GyroscopicLevelState:
        """The state at tilt `theta` (the other fields as given)."""
        return cls(log_tan_half_theta=log_tan_half(theta), phi=jnp.asarray(phi),
                   psi=jnp.asarray(psi), nutation=jnp.asarray(nutation),
                   jellet=jnp.asarray(jellet))


def _linear_state(top: TippeTop, state: State) -> GyroscopicLevelState:
    u, phi, psi, log_amplitude, J = _projection(top, state)
    return GyroscopicLevelState(
        log_tan_half_theta=u, phi=phi, psi=psi, nutation=log_amplitude, jellet=J
    )


def settle_time(top: TippeTop, state: State) -> Array:
    r"""How long the launch transient is followed in the SO(3) model: the time its nutation
    (the other root's mode, amplitude $a_0$ of the linear projection, decaying at the rate
    $-\mathrm{Im}\,r_{\rm in}$ of that mode at the nearer pole) takes to fall to
    `SETTLE_AMPLITUDE`; 0 for a launch with less, at most `SETTLE_TIME_MAX`."""
    _, _, _, log_amplitude, J = _projection(top, state)
    north = state.axis[2] >= 0
    pole = jnp.where(north, 0.0, jnp.pi).astype(log_amplitude.dtype)
    _, decay = _complex_ratio(top, pole, J, -1)
    decaying = decay < 0
    rate = jnp.where(decaying, -decay, 1.0)
    time = (log_amplitude - jnp.log(SETTLE_AMPLITUDE)) / rate
    return jnp.where(decaying, jnp.clip(time, 0.0, SETTLE_TIME_MAX), 0.0)


def _solve(term, solver, y0, t0, t1, norm):
    controller = diffrax.PIDController(rtol=SETTLE_RTOL, atol=SETTLE_ATOL, norm=norm)
    sol = diffrax.diffeqsolve(
        term, solver, t0, t1, None, y0, stepsize_controller=controller,
        saveat=diffrax.SaveAt(t1=True), max_steps=4096, throw=False,
    )
    ok = sol.result == diffrax.RESULTS.successful
    return jax.tree_util.tree_map(lambda x: x[-1], sol.ys), ok


def settle_launch(top: TippeTop, state: State) -> GyroscopicLevelState:
    r"""The fibre projection of a launch onto the slow manifold (see "Projection of a launch").

    Follows the launch in the SO(3) model for `settle_time` $T$, projects the state there
    linearly (its nutation is then about `SETTLE_AMPLITUDE`), and integrates the slow flow back
    from $T$ to the launch time. Falls back to the linear projection where either solve fails or
    $T = 0$.
    """
    linear = _linear_state(top, state)
    T = settle_time(top, state)
    short = T <= 0
    t_end = jnp.where(short, 1e-6, T).astype(T.dtype)
    so3 = SO3Level()
    rigid = so3.from_state(top, state)
    forward, ok_forward = _solve(
        diffrax.ODETerm(lambda t, y, args: so3.vector_field(t, y, top)), diffrax.Tsit5(),
        rigid, jnp.zeros_like(t_end), t_end, so3.error_norm,
    )
    settled = _linear_state(top, so3.to_state(top, forward))
    # J is exact in the SO(3) model: keep the launch's, not the solve's rounding of it
    settled = eqx.tree_at(lambda y: y.jellet, settled, linear.jellet)
    level = GyroscopicLevel()
    back, ok_back = _solve(
        diffrax.ODETerm(lambda t, y, args: level.vector_field(t, y, top)), diffrax.Tsit5(),
        settled, t_end, jnp.zeros_like(t_end), level.error_norm,
    )
    finite = jnp.all(jnp.stack([jnp.isfinite(x) for x in jax.tree_util.tree_leaves(back)]))
    use = ~short & ok_forward & ok_back & finite
    return jax.tree_util.tree_map(lambda a, b: jnp.where(use, a, b), back, linear)


class LaunchTransient(eqx.Module):
    r"""What the decay of a launch's nutation does to its slow component (see "Projection of a
    launch" in the module docstring): the integrals over the other root's mode decaying from
    the tilt $\vartheta_f$ to the pole.

    - `gain`: $I = \int (\sigma_-(\vartheta) - \sigma_-(0))\,dt$, the log of the factor by
      which the slow component's amplitude ends up changed.
    - `turn`: $\Phi$, the extra turn of its phase ($\varphi_s$).
    - `spin_turn`: $\Psi$, the extra turn of the body about the vertical ($\varphi + \psi$).
    - `valid`: the other root's mode decays along the whole path (else the integrals are 0).
    """

    gain: Array
    turn: Array
    spin_turn: Array
    valid: Array


def launch_transient(top: TippeTop, shed, J, *, north=True) -> LaunchTransient:
    r"""The integrals $I$, $\Phi$, $\Psi$ over the decay of the other root's mode from a tilt
    `shed` $= \vartheta_f$ (from the pole: $\theta = \vartheta$ at the north pole,
    $\pi - \vartheta$ at the south pole) to the pole, at Jellet `J`:

    $$I = \int_0^{\vartheta_f}\frac{\sigma_-(\vartheta) - \sigma_-(0)}{|\dot\vartheta_-|}\,
    d\vartheta,\quad
    \Phi = \int_0^{\vartheta_f}\frac{\mathrm{sgn}(J)(\nu_- - \nu_-(0)) + \Omega_- -
    \Omega_-(0)}{|\dot\vartheta_-|}\,d\vartheta,\quad
    \Psi = \int_0^{\vartheta_f}\frac{\Omega_-(1 \mp \cos\theta) \pm (n_- - n_-(0))}
    {|\dot\vartheta_-|}\,d\vartheta,$$

    with $\sigma_-$, $\nu_-$ the nutation about the other root, $\Omega_-$, $n_-$ its precession
    and spin, $\dot\vartheta_- = \mp$ (G3) its decay (upper signs at the north pole), by
    Gauss-Legendre quadrature on `AVERAGING_NODES` nodes. See "Projection of a launch".
    """
    dtype = jnp.result_type(shed, top.m)
    shed = jnp.asarray(shed, dtype)
    nodes, weights = np.polynomial.legendre.leggauss(AVERAGING_NODES)
    tilt = 0.5 * shed[..., None] * (1 + jnp.asarray(nodes, dtype))
    weight = 0.5 * shed[..., None] * jnp.asarray(weights, dtype)
    north = jnp.asarray(north)[..., None]
    side = jnp.where(north, 1.0, -1.0).astype(dtype)
    s = jnp.sin(tilt)
    x = side * jnp.cos(tilt)
    J = jnp.asarray(J, dtype)[..., None]
    other = _slow_manifold(top, x, s, J, -1)
    nutation = _nutation(top, x, s, J, other)
    at_pole = _slow_manifold(top, side, jnp.zeros_like(side), J, -1)
    nutation_pole = _nutation(top, side, jnp.zeros_like(side), J, at_pole)
    decay = -side * other.rate * s  # -d(vartheta)/dt along the other root
    moving = s > 0
    decays = decay > 0
    safe = jnp.where(decays, decay, 1.0)

    def integral(rate):
        return jnp.sum(weight * jnp.where(decays, rate / safe, 0.0), axis=-1)

    sign = _sign(J)
    gain = integral(nutation.damping - nutation_pole.damping)
    turn = integral(sign * (_safe_sqrt(nutation.frequency_squared)
                            - _safe_sqrt(nutation_pole.frequency_squared))
                    + other.precession - at_pole.precession)
    spin_turn = integral(other.precession * (1 - side * x) + side * (other.spin - at_pole.spin))
    valid = jnp.all((decays | ~moving) & (other.discriminant > 0), axis=-1)
    valid = valid & jnp.isfinite(gain) & jnp.isfinite(turn) & jnp.isfinite(spin_turn)
    zero = jnp.zeros_like(gain)
    return LaunchTransient(
        gain=jnp.where(valid, gain, zero),
        turn=jnp.where(valid, turn, zero),
        spin_turn=jnp.where(valid, spin_turn, zero),
        valid=valid,
    )


def _kept_amplitude(top: TippeTop, state: State, J, theta_b):
    r"""$(a_0, \theta_c)$: the amplitude (in $\theta$) of the nutation of a state about the other
    root's state at tilt `theta_b` with the same $J$, and the $\theta$ of its centre (reduced
    chart, conservative linearisation): $\theta_c = \theta_b + K\delta p/(M_\theta\nu^2)$,
    $a_0^2 = (\theta - \theta_c)^2 + (\delta\dot\theta/\nu)^2$."""
    theta, _, _ = euler_angles(state)
    theta_dot, phi_dot, psi_dot = euler_rates(state)
    x, s = jnp.cos(theta_b), jnp.sin(theta_b)
    base = _slow_manifold(top, x, s, J, -1)
    nutation = _nutation(top, x, s, J, base)
    nu2 = jnp.where(nutation.frequency_squared > 0, nutation.frequency_squared, 1.0)
    inertia = top.A + top.m * top.eps**2 * s * s  # M_theta
    slip = top.R * psi_dot + top.eps * phi_dot  # p of the state
    coupling = s * _momentum_coupling(top, x, s, J, base.slip)  # K
    centre = theta_b + coupling * (slip - base.slip) / (inertia * nu2)
    velocity = (theta_dot - base.theta_dot) / jnp.sqrt(nu2)
    return _safe_sqrt((theta - centre) ** 2 + velocity**2), centre


def _averaged(top: TippeTop, state: State):
    """(u, phi_s, psi_s, ln a0, J) of `average_launch`."""
    J = jellet(top, state)
    theta, _, _ = euler_angles(state)
    north = state.axis[2] >= 0
    # the launch's tilt from the nearer pole, at most NUTATION_LAUNCH_MAX (a launch with more
    # nutation is refused; one tilted further is taken only near the slow manifold)
    tilt = jnp.minimum(jnp.where(north, theta, jnp.pi - theta), NUTATION_LAUNCH_MAX)
    theta_b = jnp.where(north, tilt, jnp.pi - tilt)
    # the split with the other root's mode frozen at the launch's tilt
    c_re, c_im = _split(top, state, J, theta_b)
    a = state.axis
    kept2 = c_re**2 + c_im**2
    shed2 = (a[0] - c_re) ** 2 + (a[1] - c_im) ** 2
    # where the launch's nutation dominates: the slow component's amplitude about the other
    # root's state (reduced chart) and what the nutation's decay feeds into it; where the slow
    # component dominates, the split (exact on the slow manifold)
    weight = jnp.where(shed2 > 0, shed2 / jnp.where(shed2 > 0, shed2 + kept2, 1.0), 0.0)
    amplitude, centre = _kept_amplitude(top, state, J, theta_b)
    # the nutation decays from its centre (from the pole) to the pole
    shed = jnp.clip(jnp.where(north, centre, jnp.pi - centre), 0.0, 2 * NUTATION_LAUNCH_MAX)
    transient = launch_transient(top, shed, J, north=north)
    log_split = 0.5 * _safe_log(kept2, -2 * POLE)
    log_reduced = _safe_log(amplitude, -2 * POLE)
    log_gain = jnp.where(kept2 > 0, weight * (log_reduced + transient.gain - log_split), 0.0)
    side = jnp.where(north, 1.0, -1.0).astype(c_re.dtype)
    averaged = _slow_state(state, north, c_re, c_im, log_gain, weight * transient.turn,
                           weight * transient.spin_turn, side)
    linear = _projection(top, state)[:4]
    use = transient.valid & jnp.isfinite(c_re) & jnp.isfinite(c_im) & jnp.isfinite(log_gain)
    return (*(jnp.where(use, p, q) for p, q in zip(averaged, linear)), J)


def average_launch(top: TippeTop, state: State) -> GyroscopicLevelState:
    r"""The averaged projection of a launch onto the slow manifold (see "Projection of a
    launch" in the module docstring): $\ln\sin\theta_s = \ln a_0 + I(\vartheta_c)$, with
    $a_0$ the launch's slow content and $\vartheta_c$ its nutation's centre, both read about
    the other root's state at the launch's tilt, and $I$ what the nutation feeds into the slow
    component while it decays (`launch_transient`); where the slow component is not small
    against the nutation, the split $\xi_s = (w - r_-\xi)/(r_+ - r_-)$ (exact on the slow
    manifold). No solve: a few evaluations of (G3) and $\sigma$. Falls back to the linear
    projection where the other root's mode does not decay from the launch's tilt to the pole.
    """
    u, phi, psi, log_amplitude, J = _averaged(top, state)
    return GyroscopicLevelState(
        log_tan_half_theta=u, phi=phi, psi=psi, nutation=log_amplitude, jellet=J
    )


PROJECTIONS = ("averaged", "fibre", "linear")
"""The launch projections of `GyroscopicLevel(projection=...)`: `average_launch`,
`settle_launch`, `project_launch`."""


class GyroscopicLevel(AbstractLevel):
    r"""The slow flow (G3) for $\theta$ with $J$ fixed (see the module docstring).

    `to_state` gives the state on the slow manifold: $\theta$, $\dot\theta$ of (G3) (the slow
    drift, no nutation), $\dot\varphi = \Omega$, spin $n$ from (G1), horizontal position and
    velocity zero. `from_state` projects a state onto it (`projection`, see "Projection of a
    launch" in the module docstring). The step size is controlled on $u = \ln\tan(\theta/2)$
    alone. Where (G2) has no real root or the slow manifold repels, the run continues in the
    full model (`fallback`); with `hand_over=False` it stops there with
    `RESULTS.no_gyroscopic_balance` instead.

    **Static options:**

    - `projection`: how a launch is projected onto the slow manifold: `"averaged"` (default;
      `average_launch`, first-order averaging in closed form, no solve), `"fibre"`
      (`settle_launch`, a short SO(3) solve and a short slow solve per launch) or `"linear"`
      (`project_launch`).
    - `hand_over` (default True): where the chart ends, continue in the full model (see
      "Where the level ends"); False: the slow flow alone, stopping where the nutation it
      drops has grown past `NUTATION_MAX` (with `RESULTS.no_gyroscopic_balance`).
    - `stop_at_hand_over` (default False): with `hand_over`, stop where the run would hand
      over instead of continuing (with `RESULTS.no_gyroscopic_balance`, at the state on the
      slow manifold there), for a caller that continues the run itself: `outcome_map` does,
      in a batch of its own.
    - `hand_over_margin` (default `HAND_OVER_MARGIN`): with `hand_over`, hand over where
      $-\sigma/\nu$ falls below this.
    - `contact_margin` (default None): with `hand_over`, also hand over where the nutation
      the level carries, of amplitude $a$ and frequency $\nu$, would take the fraction
      `contact_margin` of $g$ off the normal force: where $\epsilon\sin\theta\,a\nu^2$ (the
      amplitude of the vertical acceleration of the centre of mass, $h = R - \epsilon
      \cos\theta$) reaches `contact_margin` $g$. The full model's contact loss comes where it
      reaches about $g$; the slow flow ($R_n = mg$) cannot see it.
    """

    name = "gyroscopic"
    friction_model = "so3"
    has_chart = True
    chart_end_result = "no_gyroscopic_balance"
    slow_flow = True
    projection: str = eqx.field(static=True, default="averaged")
    hand_over: bool = eqx.field(static=True, default=True)
    stop_at_hand_over: bool = eqx.field(static=True, default=False)
    hand_over_margin: float = eqx.field(static=True, default=HAND_OVER_MARGIN)
    contact_margin: float | None = eqx.field(static=True, default=None)

    def __check_init__(self):
        if self.projection not in PROJECTIONS:
            raise ValueError(f"GyroscopicLevel: projection must be one of {PROJECTIONS}, got "
                             f"{self.projection!r}.")

    def from_state(self, top, state):
        if self.projection == "fibre":
            return settle_launch(top, state)
        if self.projection == "averaged":
            return average_launch(top, state)
        return _linear_state(top, state)

    def to_state(self, top, y):
        x, s = cos_sin(y.log_tan_half_theta)
        sm = _slow_manifold(top, x, s, y.jellet)
        psi_dot = sm.spin - sm.precession * x
        theta = jnp.arctan2(s, x)
        return state_from_euler(theta, y.phi, y.psi, sm.theta_dot, sm.precession, psi_dot)

    def vector_field(self, t, y, top):
        u = y.log_tan_half_theta
        x, s = cos_sin(u)
        sm = _slow_manifold(top, x, s, y.jellet)
        nutation = _nutation(top, x, s, y.jellet, sm)
        return GyroscopicLevelState(
            log_tan_half_theta=jnp.where(jnp.abs(u) < POLE, sm.rate, 0.0),
            phi=sm.precession,
            psi=sm.spin - sm.precession * x,
            nutation=nutation.damping if y.nutation_rate is None else y.nutation_rate,
            jellet=jnp.zeros_like(y.jellet),
            nutation_rate=None if y.nutation_rate is None else jnp.zeros_like(y.nutation_rate),
        )

    def conditions(self, top, y):
        x, s = cos_sin(y.log_tan_half_theta)
        sm = _slow_manifold(top, x, s, y.jellet)
        # R'_n of eq. reactie (as `routhian_normal_force`) on the slow manifold
        eps_s = top.eps * s
        h = top.R - top.eps * x
        numerator = top.g + sm.theta_dot**2 * top.eps * x + eps_s * s * sm.precession * (
            sm.precession * x - top.C * sm.spin / top.A
        )
        denominator = 1.0 / top.m + eps_s * (eps_s + top.mu * h**2 * sm.theta_dot) / top.A
        nutation = _nutation(top, x, s, y.jellet, sm)
        return Conditions(
            contact=numerator,  # R_n D
            singular=denominator,
            upright=x,
            chart=_validity(top, x, y.jellet, y.nutation, nutation, hand_over=self.hand_over,
                            margin=self.hand_over_margin, sin_theta=s,
                            contact_margin=self.contact_margin),
        )

    def in_chart(self, top, state):
        # the linear projection's amplitude and balance decide (cheap, and what the chart reads)
        return self.conditions(top, _linear_state(top, state)).chart > 0

    def fallback(self):
        if self.hand_over and not self.stop_at_hand_over:
            return FullLevel(body=self.body)
        return None

    def error_norm(self, scaled_error):
        return jnp.abs(scaled_error.log_tan_half_theta)
