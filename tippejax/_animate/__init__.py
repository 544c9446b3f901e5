r"""Animation of a simulated top: the eccentric sphere in 3-D, drawn with matplotlib, to GIF or MP4.

Geometry (`_state.py`, paper Sec. 2): the symmetry axis $a$ points from the centre of mass $O$
to the centre $\mathcal C$ of the sphere, so the centre of the sphere is
$\mathcal C = (x + \epsilon a_x,\ y + \epsilon a_y,\ R)$ for the centre of mass at
$(x, y, R - \epsilon a_Z)$, and the contact point is $Q = \mathcal C - R e_Z$. The model is an
eccentric sphere; the stem of a real tippe top sits on the flat face opposite the centre of mass,
along $+a$ beyond $\mathcal C$ (up at $\theta = 0$, down at $\theta = \pi$). Without a modelled stem it
is drawn as a marker of the axis only, clipped at the table; a top with a `tj.Stem` has its stem
drawn as modelled, a rod along the axis to the tip's sphere of radius $r_2$ at $O + a_2 a$, and
its centre of mass at the height the run carries (`State.height`).
"""

from .draw import animate as animate
