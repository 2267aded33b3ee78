"""The `cldyn` command line: `cldyn <command> [options]`, also `python -m cldyn`.

Thin, as MuJoCo's MJX `testspeed.py`: every command parses its options, calls the public API and prints.
"""

from ._main import build_parser as build_parser, main as main
