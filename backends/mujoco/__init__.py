"""The CPU reference backend on MuJoCo itself, and MuJoCo's offscreen renderer."""
