"""`python -m posttrain.verifiers ...`: the verifier command line (`posttrain.verifiers.cli`), e.g. `python -m posttrain.verifiers list`."""
import sys

from posttrain.verifiers.cli import main

if __name__ == "__main__":
    sys.exit(main(prog="python -m posttrain.verifiers"))
