"""RoboDojo-RealEval at the robot: the operator console (`dojo console`) and blind scoring by raters.

`session` runs a real suite's trials one at a time on the `real` backend (the emulator by default) as the
operator resets scenes and starts, stops or e-stops trials; `app` serves the console and the raters' pages
(FastAPI, the optional extra `robodojo[console]`); `ratings` keeps raters' marks, their agreement and appeals
in the run's results store; `pages` is the HTML.
"""
