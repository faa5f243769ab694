"""The real backend: robot drivers behind one interface, a safety layer, and a hardware emulator.

`driver.Driver` is the interface (PiPER / PiPER X through `piper-sdk` in `piper_driver`); `safety` sits between
the policy and the driver; `realtime_sim` + `piper_emulator` are the emulated hardware that the unmodified
maker's SDK drives over a python-can bus, so all of it runs and is tested without a robot. The makers' packages
and python-can are the optional extra `robodojo[real]` (`piper_emulator` needs python-can, `piper_driver`
imports piper-sdk when it connects); the rest needs only the base install.
"""
