r"""Plots: bifurcation diagrams $J^2$ vs $\theta$, the map of the six groups, and a fit.

The first two are the pictures of the paper's Fig. 1 (blank in our copy) and of its Sec. 5, drawn
from the closed forms of the package (`branch_jellet`, `stability_function`, `thresholds`,
`group_index`). `fit_figure` draws the data, the fitted tilt and the residuals of a `FitResult`.
matplotlib is imported lazily, inside the functions; the caller chooses the backend (the CLI and the
examples use the non-interactive "Agg").

Line conventions (as in the paper's Fig. 1): solid = linearly stable, dashed = unstable. Every line
that represents steady states carries a `gid` saying what it is, so tests can check it:
`"branch-stable"`, `"branch-unstable"`, `"vertical-0-stable"`, `"vertical-0-unstable"`,
`"vertical-pi-stable"`, `"vertical-pi-unstable"`.
"""

from .bifurcation import (
    bifurcation_diagram as bifurcation_diagram,
    bifurcation_diagrams as bifurcation_diagrams,
    jellet_scale as jellet_scale,
)
from .fit import fit_figure as fit_figure
from .groups import GROUP_COLOURS as GROUP_COLOURS, group_map as group_map
from .outcomes import OUTCOME_COLOURS as OUTCOME_COLOURS, outcome_map_figure as outcome_map_figure
