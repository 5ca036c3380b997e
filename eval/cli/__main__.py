"""`python -m eval.cli`: the vitreoguard command line."""
import sys

from eval.cli import main

sys.exit(main())
