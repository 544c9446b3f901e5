"""The six bifurcation diagrams (the paper's Fig. 1) and the map of the groups.

Writes `examples/figures/bifurcation_diagrams.png` and `examples/figures/group_map.png`:

    python examples/bifurcation_diagrams.py
"""

import pathlib

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402

import tippejax as tj  # noqa: E402
from tippejax._cli import REPRESENTATIVES  # noqa: E402
from tippejax._plot import bifurcation_diagrams, group_map  # noqa: E402


def main():
    out = pathlib.Path(__file__).parent / "figures"
    out.mkdir(exist_ok=True)
    # One top per group, well inside it; C = 0.4 m R^2, m = 20 g, R = 25 mm.
    tops = {name: tj.TippeTop.from_ratios(a, e) for name, (a, e) in REPRESENTATIVES.items()}
    for name, top in tops.items():
        print(
            f"Group {name:3s}: A/C = {float(top.A_over_C):g}, eps/R = {float(top.eps_over_R):g}"
            f" -> classify: {tj.classify(top)}"
        )
    fig = bifurcation_diagrams(tops)
    fig.savefig(out / "bifurcation_diagrams.png", dpi=130)
    plt.close(fig)
    ax = group_map(points=REPRESENTATIVES)
    ax.figure.savefig(out / "group_map.png", dpi=130)
    plt.close(ax.figure)
    print(f"wrote {out / 'bifurcation_diagrams.png'} and {out / 'group_map.png'}")


if __name__ == "__main__":
    main()
