"""The runtime: the `dojo` command line, the evaluation loop, results, scoring and reports."""
