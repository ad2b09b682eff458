"""`python -m verifiers ...`: the verifier command line (`verifiers.cli`), e.g. `python -m verifiers list`."""
import sys

from verifiers.cli import main

if __name__ == "__main__":
    sys.exit(main(prog="python -m verifiers"))
