"""The `dojo` command line: one entry point, one module per subcommand, and its Hydra configuration (`config/`)."""
