"""`python -m tippejax._cli ...`, the same as the `tippejax` console script."""

from .parser import main

if __name__ == "__main__":  # (not on import: the docs build imports every module)
    raise SystemExit(main())
