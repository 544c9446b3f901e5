r"""The strategies of `fit`: attempts tried in turn, each a search for starts (or none) and a
chain of stages.

| strategy | attempts, in turn |
|---|---|
| `"global"` (default) | 0. if the guess's own residuals pass the diagnostics: `Final(final=False)`, `Final` from it; 1. from the guess: `Windows(slow=False)`, `Final(final=False)`, `Final`; 2. `GlobalSearch`, then from each of its starts `PhaseScan`, `Final(final=False)`, `Final`, and if that fails, `ValleyScan`, `Final(final=False)`, `Final` from the same start |
| `"search"` | attempt 2 of `"global"` alone |
| `"levels"` | the guess alone: `Levels`, `Windows`, `Final` |
| `"windows"` | the guess alone: `Windows(slow=False)`, `Final` |
| `"plain"` | the guess alone: `Final` |

After each start the residuals are tested (`diagnostics.py`); the fit stops at the first start
whose residuals pass, and otherwise returns the fit with the lowest loss of all, flagged
`local_minimum`. A guess whose residuals are already noise is in the right valley: it is only
polished (early windows leave some directions free, and a scan on noisy data can pick a
neighbouring cycle, so neither is run from a guess that needs neither). The windows from the guess cost a few simulations of the record and succeed
when the guess is close enough for the phase to be followed window by window; the search
covers the guesses it cannot follow (a factor 2 either way). Its two chains find the
nutation's phase in two ways: `PhaseScan` scans the spin alone on an early window, which is
cheap and right where the nutation shows early; `ValleyScan` first puts the start on the slow
loss's valley and scans along it, which is right where the early window is long (a slowly
rising record) and the nutation is below the noise, so that a spin scanned alone would make up
for the other parameters' error in the slow rise. Each start tries them in that order.

The searches and scans (`GlobalSearch`, `PhaseScan`, `ValleyScan`) simulate a law whose motion
converges as its slip scale goes to 0 (`CoulombContensou`) at a slip scale of at least
`setup.SEARCH_SLIP_SCALE`: they rank and propose, and a trial top that stops drilling would
otherwise cost of the order of 1/slip_scale steps. The `Windows` and `Final` stages, which fit,
simulate the law as given.

An attempt is `(search, chain)` or `(search, (chain, chain, ...))`: a chain is a tuple of
stages; alternative chains are tried in turn from each start.
"""

from __future__ import annotations

from .stages import Final, GlobalSearch, Levels, PhaseScan, ValleyScan, Windows

IF_NOISE = "if the guess's residuals are noise"  # a search: the guess, or no start at all
_POLISH = (IF_NOISE, (Final(final=False), Final()))
_WINDOWS = (None, (Windows(slow=False), Final(final=False), Final()))
_SEARCH = (
    GlobalSearch(),
    ((PhaseScan(), Final(final=False), Final()), (ValleyScan(), Final(final=False), Final())),
)

STRATEGIES = {
    "global": (_POLISH, _WINDOWS, _SEARCH),
    "search": (_SEARCH,),
    "levels": ((None, (Levels(), Windows(), Final())),),
    "windows": ((None, (Windows(slow=False), Final())),),
    "plain": ((None, (Final(),)),),
}
