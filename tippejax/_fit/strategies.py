r"""The strategies of `fit`: a search for starts (or none) and a chain of stages.

| strategy | search | stages |
|---|---|---|
| `"global"` (default) | `GlobalSearch` | `PhaseScan`, `Final(final=False)`, `Final` |
| `"levels"` | the guess alone | `Levels`, `Windows`, `Final` |
| `"windows"` | the guess alone | `Windows(slow=False)`, `Final` |
| `"plain"` | the guess alone | `Final` |

With a search, the starts are refined in turn, best first, until one ends with residuals that
pass the diagnostics (`diagnostics.py`); if none does, the fit with the lowest loss is returned
and flagged `local_minimum`.
"""

from __future__ import annotations

from .stages import Final, GlobalSearch, Levels, PhaseScan, Windows

STRATEGIES = {
    "global": (GlobalSearch(), (PhaseScan(), Final(final=False), Final())),
    "levels": (None, (Levels(), Windows(), Final())),
    "windows": (None, (Windows(slow=False), Final())),
    "plain": (None, (Final(),)),
}
