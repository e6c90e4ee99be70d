"""Subcommands of the `imugraph` command line (see `imugraph.cli` and DESIGN.md, "Command line").

One module per command group, each exposing `run(args: argparse.Namespace) -> int`:
`calibrate` (calibrate, smooth), `demo`, `simulate`; shared helpers live in `common` (paths, progress,
scores, output files) and `report` (the printed result tables).
"""
