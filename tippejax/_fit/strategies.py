r"""The strategies of `fit`: attempts tried in turn, each a search for starts (or none) and a
chain of stages.

| strategy | attempts, in turn |
|---|---|
| `"global"` (default) | 1. from the guess: `Windows(slow=False)`, `Final(final=False)`, `Final`; 2. `GlobalSearch`, then `PhaseScan`, `Final(final=False)`, `Final` |
| `"search"` | attempt 2 of `"global"` alone |
| `"levels"` | the guess alone: `Levels`, `Windows`, `Final` |
| `"windows"` | the guess alone: `Windows(slow=False)`, `Final` |
| `"plain"` | the guess alone: `Final` |

After each start the residuals are tested (`diagnostics.py`); the fit stops at the first start
whose residuals pass, and otherwise returns the fit with the lowest loss of all, flagged
`local_minimum`. The windows from the guess cost a few simulations of the record and succeed
when the guess is close enough for the phase to be followed window by window; the search
covers the guesses it cannot follow (a factor 2 either way).
"""

from __future__ import annotations

from .stages import Final, GlobalSearch, Levels, PhaseScan, Windows

_WINDOWS = (None, (Windows(slow=False), Final(final=False), Final()))
_SEARCH = (GlobalSearch(), (PhaseScan(), Final(final=False), Final()))

STRATEGIES = {
    "global": (_WINDOWS, _SEARCH),
    "search": (_SEARCH,),
    "levels": ((None, (Levels(), Windows(), Final())),),
    "windows": ((None, (Windows(slow=False), Final())),),
    "plain": ((None, (Final(),)),),
}
