"""The built-in asset library: one annotated YAML per asset, with the small mesh files it names (package data)."""
