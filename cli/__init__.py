"""statfit's command-line front end (installed as ``statfit_cli``): parse, call the library, print.

Its modules import typer, rich and only the library's torch-free modules (the options' defaults and
help texts); each command imports what it calls when it runs, so ``--help`` and a refused option
answer without loading torch (tests/test_cli.py)."""
