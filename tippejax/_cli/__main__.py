"""`python -m tippejax._cli ...`, the same as the `tippejax` console script."""

from .parser import main

raise SystemExit(main())
