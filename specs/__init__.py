"""The built-in specs (schemas, robots, tasks, suites), shipped as package data and found with importlib.resources."""
