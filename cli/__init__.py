"""The `leco` command line: the top of the layers (it may import model, workers, service and bench;
none of them imports it). Subcommands import their layer lazily so `leco scene ...` stays light."""
