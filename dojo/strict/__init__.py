"""`dojo validate --strict`: the checks a contributed task pack must pass, the work they run and their report."""
