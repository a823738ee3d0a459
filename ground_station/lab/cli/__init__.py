"""The research subcommands' options and runs (`qnav study`, `qnav sweep`): the thin
`ground_station.commands.study` / `.sweep` modules hand their subparsers here."""
