"""The compiler: spec files -> validated specs -> sampled scenes -> MuJoCo models -> content-addressed plans."""
