"""`python -m posttrain ...` (used with `accelerate launch -m posttrain ...`)."""
import sys

from posttrain.cli import main

sys.exit(main())
