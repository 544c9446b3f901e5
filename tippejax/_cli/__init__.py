"""The command line, `tippejax classify | diagram | demo | fit | map | animate`."""

from .common import REPRESENTATIVES as REPRESENTATIVES
from .parser import main as main
