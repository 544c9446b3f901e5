"""The `tippejax` command line: its parser, one sub-command per module, and `main`."""

from __future__ import annotations

import argparse
from collections.abc import Sequence

from .._fit import FREE_NAMES, METHODS, STRATEGIES
from .._simulate import MODELS
from . import animate, classify, demo, diagram, fit, maps
from .animate import ANIMATE_DEFAULT_OUT
from .common import DEFAULT_OUT
from .fit import FIT_DEFAULT_SPIN, FIT_MIN_THETA0
from .maps import MAP_GROUP_TOPS


def build_parser() -> argparse.ArgumentParser:
    """The parser of `tippejax`: one sub-command per module of `tippejax._cli`."""
    parser = argparse.ArgumentParser(
        prog="tippejax", description="Steady states and groups of the tippe top (tippejax)."
    )
    sub = parser.add_subparsers(dest="command", required=True)

    def out_option(p):
        p.add_argument(
            "--out",
            metavar="DIR",
            default=DEFAULT_OUT,
            help=f"output folder (default ./{DEFAULT_OUT})",
        )

    p = sub.add_parser("classify", help="group and thresholds of a top; writes group_map.png")
    p.add_argument("--A-over-C", dest="A_over_C", type=float, default=None, help="A/C (>= 0.5)")
    p.add_argument(
        "--eps-over-R", dest="eps_over_R", type=float, default=None, help="eps/R in (0, 1)"
    )
    out_option(p)
    p.set_defaults(func=classify.run)

    p = sub.add_parser("diagram", help="writes bifurcation_diagrams.png and group_map.png")
    out_option(p)
    p.set_defaults(func=diagram.run)

    p = sub.add_parser("demo", help="steady states of the default top launched near upright")
    out_option(p)
    p.add_argument(
        "--spin",
        type=float,
        default=None,
        help="launch spin n0 (rad/s); default 1.5 x the inversion threshold, rounded up",
    )
    p.add_argument("--theta0", type=float, default=0.1, help="launch tilt (rad), default 0.1")
    p.set_defaults(func=demo.run)

    p = sub.add_parser(
        "fit",
        help="fit a top's parameters to a measured tilt theta(t) in a CSV file",
        description=(
            "Fit free parameters of the top and its launch to a measured tilt theta(t) with "
            "tippejax.fit. DATA.csv has a header row with columns t (s) and theta (rad), "
            "optionally phi (rad, the precession angle, fitted too); an empty cell or nan is a "
            "missing sample. The starting guess is the default top (A/C 0.9, eps/R 0.3, "
            "m 0.02 kg, R 0.025 m, mu 0.3 s/m) with the fields given below replaced. Prints the "
            "fitted values with standard errors and writes fit.png and fit.csv "
            "(t, theta_obs, theta_fit, residual) to --out."
        ),
    )
    p.add_argument("data", metavar="DATA.csv", help="the data: columns t, theta[, phi]")
    p.add_argument(
        "--free",
        metavar="NAMES",
        default="mu,eps,spin",
        help=f"comma-separated names of the parameters to fit (default mu,eps,spin), from: "
        f"{','.join(FREE_NAMES)}",
    )
    guess = p.add_argument_group("starting guess (default: the default top)")
    guess.add_argument("--m", type=float, default=None, help="mass (kg), default 0.02")
    guess.add_argument(
        "--R", type=float, default=None, help="radius of the sphere (m), default 0.025"
    )
    guess.add_argument(
        "--eps",
        type=float,
        default=None,
        help="centre of sphere to centre of mass (m), default 0.0075",
    )
    guess.add_argument(
        "--A-over-C",
        dest="A_over_C",
        metavar="X",
        type=float,
        default=None,
        help="A/C, default 0.9. --A-over-C or --eps-over-R rebuild the top with "
        "TippeTop.from_ratios (keeping m, R, mu; C = 0.4 m R^2)",
    )
    guess.add_argument(
        "--eps-over-R",
        dest="eps_over_R",
        metavar="Y",
        type=float,
        default=None,
        help="eps/R in (0, 1), default 0.3 (not together with --eps)",
    )
    guess.add_argument(
        "--mu", type=float, default=None, help="viscous friction coefficient (s/m), default 0.3"
    )
    guess.add_argument(
        "--theta0",
        metavar="TH",
        type=float,
        default=None,
        help="launch tilt (rad) at the launch time t0, held fixed unless --free names "
        "theta0; default: free, starting from the mean of the record's first "
        f"samples (at least {FIT_MIN_THETA0:g})",
    )
    guess.add_argument(
        "--theta-dot",
        dest="theta_dot",
        metavar="W",
        type=float,
        default=None,
        help="launch tilt rate (rad/s), default 0; for a top launched upright give "
        "--theta0 0 --theta-dot W and free theta_dot",
    )
    guess.add_argument(
        "--spin",
        metavar="N",
        type=float,
        default=FIT_DEFAULT_SPIN,
        help=f"launch spin (rad/s), default {FIT_DEFAULT_SPIN:g}",
    )
    guess.add_argument(
        "--t0",
        metavar="T0",
        type=float,
        default=None,
        help="launch time (s) in the record's clock: the guess is the state at "
        "t0 (default 0, as in tippejax.fit and simulate; free it with "
        "--free ...,t0)",
    )
    p.add_argument(
        "--model",
        default="full",
        choices=("full", "so3", "routhian"),
        help="level of model to fit with (default full)",
    )
    p.add_argument(
        "--strategy",
        default="global",
        choices=tuple(STRATEGIES),
        help="fitting strategy (default global: a batch of starts ranked by the "
        "smoothed tilt, then the best refined until its residuals are noise)",
    )
    p.add_argument(
        "--sigma",
        type=float,
        default=None,
        help="noise of theta (rad), if known: the residuals are tested against it",
    )
    p.add_argument(
        "--trim",
        action="store_true",
        help="refit on the part of the record the model describes (a stem landing)",
    )
    p.add_argument(
        "--method",
        default="levenberg_marquardt",
        choices=METHODS,
        help="optimiser (default levenberg_marquardt)",
    )
    p.add_argument(
        "--max-steps",
        dest="max_steps",
        metavar="K",
        type=int,
        default=100,
        help="optimiser steps per optimisation (default 100)",
    )
    p.add_argument(
        "--t-max",
        dest="t_max",
        metavar="T",
        type=float,
        default=None,
        help="use only the samples with t <= T (s): the part of the record the model describes",
    )
    p.add_argument(
        "--no-phi", dest="no_phi", action="store_true", help="ignore a phi column (fit theta only)"
    )
    out_option(p)
    p.set_defaults(func=fit.run)

    p = sub.add_parser(
        "animate",
        help="simulate a launch and write a 3-D animation (GIF or MP4)",
        description=(
            "Simulate one launch (default: the default top of `tippejax demo`, theta0 0.1 rad, "
            "spin 1.5 x the inversion threshold) and render it with tippejax.animate: the sphere, "
            "its stem, the spin marker and the contact-point trace. Real time by default; the "
            "spin (~100 rad/s) aliases at any frame rate a GIF can show, so pass --speed 0.2 "
            "(slow motion) to watch it."
        ),
    )
    top_group = p.add_argument_group("the top (default: the default top)")
    top_group.add_argument("--m", type=float, default=None, help="mass (kg), default 0.02")
    top_group.add_argument("--R", type=float, default=None, help="radius (m), default 0.025")
    top_group.add_argument(
        "--eps",
        type=float,
        default=None,
        help="centre of sphere to centre of mass (m), default 0.0075",
    )
    top_group.add_argument(
        "--A-over-C",
        dest="A_over_C",
        metavar="X",
        type=float,
        default=None,
        help="A/C, default 0.9 (rebuilds the top with TippeTop.from_ratios)",
    )
    top_group.add_argument(
        "--eps-over-R",
        dest="eps_over_R",
        metavar="Y",
        type=float,
        default=None,
        help="eps/R in (0, 1), default 0.3",
    )
    top_group.add_argument(
        "--mu", type=float, default=None, help="viscous friction coefficient (s/m), default 0.3"
    )
    p.add_argument("--theta0", type=float, default=0.1, help="launch tilt (rad), default 0.1")
    p.add_argument(
        "--spin",
        type=float,
        default=None,
        help="launch spin n0 (rad/s); default 1.5 x the inversion threshold",
    )
    p.add_argument("--t1", type=float, default=12.0, help="simulated time (s), default 12")
    p.add_argument("--model", default="full", choices=MODELS, help="level of model (default full)")
    p.add_argument("--fps", type=float, default=20.0, help="frames per second (default 20)")
    timing = p.add_mutually_exclusive_group()
    timing.add_argument(
        "--speed",
        type=float,
        default=None,
        help="seconds simulated per second shown (default 1; < 1: slow motion)",
    )
    timing.add_argument(
        "--duration", type=float, default=None, help="seconds of animation for the whole span"
    )
    timing.add_argument("--frames", type=int, default=None, help="number of frames")
    p.add_argument(
        "--t-start",
        dest="t_start",
        type=float,
        default=None,
        help="first time shown (s), default 0",
    )
    p.add_argument(
        "--t-end",
        dest="t_end",
        type=float,
        default=None,
        help="last time shown (s), default the end of the run",
    )
    p.add_argument("--dpi", type=float, default=80.0, help="dots per inch (5 x 5 in frames)")
    p.add_argument(
        "--follow", action="store_true", help="keep the sphere in the middle of the view"
    )
    p.add_argument(
        "--out",
        metavar="PATH",
        default=ANIMATE_DEFAULT_OUT,
        help=f"output file, .gif or .mp4 (needs ffmpeg); default {ANIMATE_DEFAULT_OUT}",
    )
    p.set_defaults(func=animate.run)

    p = sub.add_parser(
        "map",
        help="outcome maps: where launches end over theta0 x spin, and over (A/C, eps/R)",
        description=(
            "Simulate a grid of launches theta0 x spin of one top with tippejax.outcome_map and "
            "plot where each ends (upright, inverted, intermediate, contact lost, failed) with "
            "the linear-theory boundaries; then a grid of tops over (A/C, eps/R) for one launch "
            "beside the group map. Writes outcome_map.png, outcome_map.npz and "
            "outcome_map_tops.png to --out. With --adaptive the map is computed from a "
            "coarse base grid, simulating only where outcomes change, and drawn with its "
            "boundaries, the linear theory's curves and the launches simulated; the .npz "
            "holds the outcomes, the flags, the boundaries and the axes."
        ),
    )
    p.add_argument(
        "--group",
        choices=MAP_GROUP_TOPS,
        default="standard",
        help="the top: the standard top (default) or a representative of a group",
    )
    p.add_argument(
        "--A-over-C",
        dest="A_over_C",
        metavar="X",
        type=float,
        default=None,
        help="A/C (replaces the group's)",
    )
    p.add_argument(
        "--eps-over-R",
        dest="eps_over_R",
        metavar="Y",
        type=float,
        default=None,
        help="eps/R (replaces the group's)",
    )
    p.add_argument("--mu", type=float, default=None, help="friction (s/m), default 0.3")
    p.add_argument("--n-theta", dest="n_theta", type=int, default=12, help="launch tilts (12)")
    p.add_argument("--n-spin", dest="n_spin", type=int, default=24, help="launch spins (24)")
    p.add_argument(
        "--resolution",
        type=int,
        default=None,
        help="launches along each axis (replaces --n-theta and --n-spin)",
    )
    p.add_argument(
        "--adaptive",
        action="store_true",
        help="an adaptive map (tj.outcome_map(..., refine=k)) from a base grid of "
        "about 32 cells per axis",
    )
    p.add_argument(
        "--refine",
        type=int,
        default=None,
        help="levels of refinement of an adaptive map (default with --adaptive: "
        "about log2(resolution / 32))",
    )
    p.add_argument("--theta-min", dest="theta_min", type=float, default=0.02)
    p.add_argument("--theta-max", dest="theta_max", type=float, default=1.5)
    p.add_argument("--spin-min", dest="spin_min", type=float, default=10.0)
    p.add_argument(
        "--spin-max", dest="spin_max", type=float, default=None, help="default 6 x n1 of the top"
    )
    p.add_argument("--t1", type=float, default=30.0, help="simulated time (s), default 30")
    p.add_argument("--model", default="full", choices=MODELS, help="level of model (full)")
    p.add_argument(
        "--tolerance",
        type=float,
        default=None,
        help="for --model auto: largest theta error (rad) a level may make",
    )
    p.add_argument(
        "--no-tops", dest="tops", action="store_false", help="skip the map over (A/C, eps/R)"
    )
    p.add_argument(
        "--n-tops",
        dest="n_tops",
        type=int,
        default=16,
        help="A/C values of the top map (eps/R gets 3/4 as many)",
    )
    p.add_argument(
        "--theta0-tops",
        dest="theta0_tops",
        type=float,
        default=0.1,
        help="launch tilt of the top map (rad), default 0.1",
    )
    p.add_argument(
        "--spin-tops",
        dest="spin_tops",
        type=float,
        default=None,
        help="launch spin of the top map (default: the middle of the spin range)",
    )
    p.add_argument(
        "--out", metavar="DIR", default=DEFAULT_OUT, help=f"output folder, default {DEFAULT_OUT}"
    )
    p.set_defaults(func=maps.run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the `tippejax` console script.

    **Returns:** the exit status: 0, or 2 for bad input to `fit` (the message goes to stderr).
    """
    args = build_parser().parse_args(argv)
    return args.func(args)
