"""One module per `bagit` subcommand.

Each module defines `NAME`, `HELP`, `add_arguments(parser)` and `run(args) -> dict`. `run`
returns the machine-readable result (printed as JSON with `--json`); a result with
`"success": false` exits with status 1. Heavy imports happen inside `run`, so `bagit --help`
stays fast.
"""
