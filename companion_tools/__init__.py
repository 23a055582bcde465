"""Tools that evaluate and benchmark the companion (eval, bench, replay), apart from the runtime as
pytracking keeps its evaluation apart: they may import the runtime and the back-end; `cloudtrack-companion`
finds their subcommands through the `cloudtrack.companion_commands` entry points and never imports them."""
