"""`simulate` and its plumbing: argument checks, the compiled programs of a run, and the batch
with shared steps."""

from .single import MODELS as MODELS, simulate as simulate, simulate_tilt as simulate_tilt
