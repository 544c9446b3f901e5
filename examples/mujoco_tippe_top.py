"""A tippe-top trajectory from an independent physics engine, MuJoCo, for fitting tests.

The top is the eccentric sphere of `tippejax.default_top()` (R = 25 mm, m = 20 g,
eps = 0.3 R, C = 2/5 m R^2, A = B = 0.9 C), but the contact is MuJoCo's: a soft,
Coulomb-friction point contact instead of our hard contact with viscous friction.

Model (MJCF, built below as a string):

- one free body whose frame sits at the centre of mass O, body z axis = symmetry axis a,
  pointing from O to the centre of the sphere; the sphere geom is at (0, 0, eps) and the
  `inertial` element gives the mass and diaginertia (A, A, C) about O (it overrides the
  geoms' own masses, so an optional stem adds geometry but no mass);
- `--stem`: a thin capsule on top of the sphere (the side away from O), as on a real top;
  when the top turns over it lands on it, so theta then stays short of pi;
- condim 3: sliding friction only, like our model. condim 4/6 add torsional/rolling friction;
  with MuJoCo's default coefficients (0.005, 0.0001) they brake the spin and the top no longer
  turns over. Elliptic friction cone (isotropic Coulomb friction, not MuJoCo's default
  pyramid); friction coefficient mu = 0.3 (a hard plastic/wood top on a table);
- a stiff contact, solref (2 ms, 1): penetration ~5-11 um instead of the ~0.4-0.6 mm of
  MuJoCo's default 20 ms; RK4 with timestep 1e-4 s (theta(t) is converged in the timestep
  there; implicitfast needs ~1e-5 s for the same). Energy never rises between samples.

Caveats (measured): (1) MuJoCo's friction is regularized: below the Coulomb limit the contact
creeps at a few mm/s instead of sticking, and that creep is what makes the top rise out of the
near-upright phase, so the inversion time depends on the contact softness (solref 1/2/4/10 ms:
t(pi/2) = 1.50/1.07/0.88/0.74 s), not only on mu. (2) While sliding fast, the convex contact
model pushes the ball up by ~mu |v_slip| dt each step: it hops by a few um and is out of
contact in most steps during the fast rise (t ~ 0.5-1.3 s).

theta = angle between the vertical and a (0: resting, centre of mass low; pi: inverted),
phi = precession angle, a = (sin theta sin phi, -sin theta cos phi, cos theta) as in
`tippejax`, unwrapped (ill-defined, hence noisy, while sin theta ~ 0).

    python examples/mujoco_tippe_top.py [--spin 100] [--theta0 0.1] [--friction 0.3] [--stem]

writes `t,theta,phi` at 200 Hz to `examples/data/mujoco_tippe_top.csv`.
"""

import argparse
import pathlib
import time

import mujoco
import numpy as np

R, M, EPS_R, A_C = 0.025, 0.02, 0.3, 0.9
C = 0.4 * M * R**2
A = A_C * C
EPS = EPS_R * R
STEM_RADIUS, STEM_LENGTH = 0.003, 0.012  # capsule radius, length of its segment (m)


def build_xml(
    friction,
    stem=False,
    condim=3,
    solref=(0.002, 1.0),
    timestep=1e-4,
    integrator="RK4",
    cone="elliptic",
):
    """The MJCF model: a plane floor and a free eccentric sphere (frame at the centre of mass)."""
    # Torsional/rolling coefficients: MuJoCo's defaults, used only with condim 4 or 6.
    contact = (
        f'condim="{condim}" friction="{friction} 0.005 0.0001" solref="{solref[0]} {solref[1]}"'
    )
    z0 = EPS + 0.8 * R  # the stem leaves the sphere on the side away from the centre of mass
    stem_geom = (
        f'<geom name="stem" type="capsule" size="{STEM_RADIUS}" '
        f'fromto="0 0 {z0} 0 0 {z0 + STEM_LENGTH}" {contact}/>'
        if stem
        else ""
    )
    return f"""
<mujoco model="tippe_top">
  <option timestep="{timestep}" integrator="{integrator}" cone="{cone}" gravity="0 0 -9.81">
    <flag energy="enable"/>
  </option>
  <worldbody>
    <geom name="floor" type="plane" size="0 0 1" {contact}/>
    <body name="top">
      <freejoint/>
      <inertial pos="0 0 0" mass="{M}" diaginertia="{A} {A} {C}"/>
      <geom name="ball" type="sphere" size="{R}" pos="0 0 {EPS}" {contact}/>
      {stem_geom}
    </body>
  </worldbody>
</mujoco>"""


def axis_angles(data):
    """theta and phi (not unwrapped) of the symmetry axis: the body z axis in the world frame."""
    a = data.xmat[1].reshape(3, 3)[:, 2]
    return np.arctan2(np.hypot(a[0], a[1]), a[2]), np.arctan2(a[0], -a[1])


def simulate(spin, theta0, friction, duration, stem=False, rate=200.0, **options):
    """Run MuJoCo; return (t, theta, phi) at `rate` Hz and diagnostics of the contact."""
    model = mujoco.MjModel.from_xml_string(build_xml(friction, stem, **options))
    data = mujoco.MjData(model)
    # Tilt about the world x axis: a = (0, -sin theta0, cos theta0), i.e. phi = 0.
    data.qpos[:3] = (0.0, EPS * np.sin(theta0), R - EPS * np.cos(theta0))  # sphere touches
    data.qpos[3:7] = (np.cos(theta0 / 2), np.sin(theta0 / 2), 0.0, 0.0)
    data.qvel[:] = 0.0
    data.qvel[5] = spin  # free joint: angular velocity in the body frame, spin about body z
    mujoco.mj_forward(model, data)
    energy0 = data.energy.sum()

    per_sample = max(1, round(1.0 / (rate * model.opt.timestep)))
    n_samples = int(round(duration * rate)) + 1
    out = np.empty((n_samples, 3))
    max_pen = max_gap = 0.0
    steps_without_contact = 0
    max_energy_rise = 0.0
    energy_prev = energy0
    for k in range(n_samples):
        theta, phi = axis_angles(data)
        out[k] = data.time, theta, phi
        if k == n_samples - 1:
            break
        for _ in range(per_sample):
            mujoco.mj_step(model, data)
            if data.ncon == 0:
                steps_without_contact += 1
            else:
                max_pen = max(max_pen, -data.contact.dist.min())
            # Height of the lowest point of the sphere above the floor (> 0: airborne).
            centre_z = data.xpos[1, 2] + data.xmat[1, 8] * EPS
            max_gap = max(max_gap, centre_z - R)
        energy = data.energy.sum()
        max_energy_rise = max(max_energy_rise, energy - energy_prev)
        energy_prev = energy
    out[:, 2] = np.unwrap(out[:, 2])
    diagnostics = dict(
        steps=(n_samples - 1) * per_sample,
        max_penetration=max_pen,
        max_gap=max_gap,
        steps_without_contact=steps_without_contact,
        energy0=energy0,
        energy1=data.energy.sum(),
        max_energy_rise=max_energy_rise,
    )
    return out, diagnostics


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--spin", type=float, default=100.0, help="spin n about the axis (rad/s)")
    parser.add_argument("--theta0", type=float, default=0.1, help="initial tilt (rad)")
    parser.add_argument("--friction", type=float, default=0.3, help="Coulomb coefficient")
    parser.add_argument("--stem", action="store_true", help="add a massless stem on top")
    parser.add_argument("--duration", type=float, default=8.0, help="simulated time (s)")
    parser.add_argument("--condim", type=int, default=3, choices=(3, 4, 6))
    parser.add_argument("--solref", type=float, nargs=2, default=(0.002, 1.0))
    parser.add_argument("--timestep", type=float, default=1e-4)
    parser.add_argument(
        "--integrator", default="RK4", choices=("Euler", "RK4", "implicit", "implicitfast")
    )
    parser.add_argument("--cone", default="elliptic", choices=("elliptic", "pyramidal"))
    parser.add_argument(
        "--out",
        type=pathlib.Path,
        default=pathlib.Path(__file__).parent / "data" / "mujoco_tippe_top.csv",
    )
    args = parser.parse_args()

    start = time.perf_counter()
    traj, diag = simulate(
        args.spin,
        args.theta0,
        args.friction,
        args.duration,
        args.stem,
        condim=args.condim,
        solref=tuple(args.solref),
        timestep=args.timestep,
        integrator=args.integrator,
        cone=args.cone,
    )
    wall = time.perf_counter() - start

    args.out.parent.mkdir(parents=True, exist_ok=True)
    np.savetxt(args.out, traj, delimiter=",", header="t,theta,phi", comments="", fmt="%.9g")
    t, theta = traj[:, 0], traj[:, 1]
    crossed = np.nonzero(theta > np.pi / 2)[0]
    if crossed.size:
        i = crossed[0]  # linear interpolation between the two samples around pi/2
        frac = (np.pi / 2 - theta[i - 1]) / (theta[i] - theta[i - 1])
        t_half = t[i - 1] + frac * (t[i] - t[i - 1])
        print(f"theta first crosses pi/2 at t = {t_half:.3f} s")
    else:
        print("theta never crosses pi/2")
    print(
        f"final theta = {theta[-1]:.4f} rad (pi - theta = {np.pi - theta[-1]:.2e}), "
        f"max theta = {theta.max():.4f}"
    )
    print(
        f"max penetration = {diag['max_penetration'] * 1e6:.2f} um, max ball lift-off = "
        f"{diag['max_gap'] * 1e6:.2f} um, steps without contact = "
        f"{diag['steps_without_contact']} of {diag['steps']}"
    )
    print(
        f"energy {diag['energy0'] * 1e3:.4f} mJ -> {diag['energy1'] * 1e3:.4f} mJ, largest rise "
        f"between samples {diag['max_energy_rise'] * 1e6:.3g} uJ"
    )
    print(f"wall time = {wall:.2f} s; wrote {args.out}")


if __name__ == "__main__":
    main()
