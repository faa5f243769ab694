"""Scores as RoboDojo reports them, and the report built from stored episodes (JSON, HTML, SVG charts)."""
