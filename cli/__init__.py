"""statfit's command-line front end (installed as ``statfit_cli``): parse, call the library, print."""
