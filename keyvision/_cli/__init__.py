"""The `keyvision` command line: `keyvision <command> [options]`, also `python -m keyvision`.

Thin, as cldyn's: every command parses its options, calls the public API and prints. The error path,
the argument types and the output checks are cldyn's (`cldyn._cli`), so both programs refuse the same
values with the same words.
"""

from ._main import build_parser as build_parser, main as main
