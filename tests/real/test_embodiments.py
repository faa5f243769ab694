"""The real backend on the other two RealEval embodiments, emulated: the PiPER X through the unmodified
piper-sdk over the emulator's CAN buses (the PiPER's protocol), the ARX X5 at joint level (its protocol is
inside ARX's closed library; see dojo/backends/real/robots/arx_x5_bimanual.yaml). For each: the arms hold
under a hold-still policy with nothing refused, a commanded move happens, an e-stop ends the episode and returns
the arms to the reset pose, and hardware for the ARX X5 is refused with the reason.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("can")
pytest.importorskip("piper_sdk")

from dojo.backends.real.backend import END_ESTOP, RealBackend  # noqa: E402
from dojo.backends.real.joint_level_driver import JointLevelDriver  # noqa: E402
from dojo.backends.real.piper_driver import PiperDriver  # noqa: E402
from dojo.compiler.plan import compile_plan  # noqa: E402
from dojo.compiler.spec_library import SpecLibrary  # noqa: E402

PACK = Path(__file__).parent / "pack"
DRIVERS = {"piperx_block_probe": PiperDriver, "arx_x5_block_probe": JointLevelDriver}


def _plan(task: str):
    library = SpecLibrary.load([PACK], strict=False)
    return compile_plan(library, library.get("task", task), "standard", 0)


@pytest.mark.parametrize("task", sorted(DRIVERS))
def test_the_embodiment_holds_moves_and_returns_home_on_an_e_stop(task: str, figures) -> None:
    plan = _plan(task)
    with RealBackend() as real:
        real.load([plan])
        obs = real.reset()[0]
        driver = real._driver
        assert isinstance(driver, DRIVERS[task])
        start = obs["state"]["joint_pos"].reshape(2, 7)
        for _ in range(10):  # hold still: the observed pose commanded back
            result = real.step(obs["state"]["joint_pos"][None])
            obs = result.obs[0]
        assert all(v == 0 for k, v in result.counters[0].items() if k.startswith("refused"))
        assert np.abs(obs["state"]["joint_pos"].reshape(2, 7) - start).max() < 0.02
        target = start.copy()
        target[0, 0] += 0.3  # the left arm's base joint, 0.3 rad over 15 steps (0.6 s)
        for k in range(1, 16):
            result = real.step((start + (target - start) * k / 15).reshape(1, 14))
        time.sleep(0.3)
        moved = float(driver.read().joint_pos[0, 0] - start[0, 0])
        assert moved > 0.25, moved
        real.safety.estop()
        result = real.step(target.reshape(1, 14))
        assert result.done[0] and result.end_reason == [END_ESTOP]
        started, home = time.monotonic(), driver.home_pose[0]
        while np.abs(driver.read().joint_pos - home).max() > 0.01 and time.monotonic() - started < 15:
            time.sleep(0.01)
        figures.add(f"{plan.embodiment}.estop_return_s(0.3 rad away)", round(time.monotonic() - started, 2))
        assert np.abs(driver.read().joint_pos - home).max() <= 0.01


def test_arx_x5_hardware_is_refused_with_the_reason() -> None:
    with RealBackend(driver="piper") as real, pytest.raises(ValueError, match="no hardware driver yet"):
        real.load([_plan("arx_x5_block_probe")])
