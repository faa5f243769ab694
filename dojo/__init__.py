"""RoboDojo: a benchmark compiler for generalist robot manipulation policies (specs -> compiler -> plans -> runtime <-> backends / policies)."""
