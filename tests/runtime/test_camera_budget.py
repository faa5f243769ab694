"""What a run says before it renders cameras for a policy, and which image size it renders."""

from __future__ import annotations

from xpolicylab.model import PolicyMetadata

from dojo.evaluation.camera_budget import budget_message, image_size

CAMERAS = ("head", "left_wrist", "right_wrist")


def test_the_policy_declared_size_unless_the_user_sets_one() -> None:
    declared = PolicyMetadata(name="p", cameras=CAMERAS, image_width=320, image_height=240)
    assert image_size(declared, None, None) == (320, 240, None)
    any_size = PolicyMetadata(name="q", cameras=CAMERAS, image_width=None, image_height=None)
    assert image_size(any_size, None, None) == (640, 480, None)  # RoboDojo's default
    assert image_size(any_size, 224, 224) == (224, 224, None)  # it accepts any size: nothing to warn about
    width, height, warning = image_size(declared, 224, 224)
    assert (width, height) == (224, 224)
    assert warning == "policy p declares 320x240 images; sending 224x224 as width/height ask (the policy must resize them)"


def test_the_message_counts_images_and_suggests_smaller_ones() -> None:
    meta = PolicyMetadata(name="mine", cameras=CAMERAS, chunk_size=8)
    line = budget_message(meta, CAMERAS, 640, 480, horizons=[600, 300], rate=50.0)
    # ceil(600 / 8) + ceil(300 / 8) = 75 + 38 policy calls, three images each.
    assert line.startswith("policy mine reads 3 camera(s) (head, left_wrist, right_wrist) at 640x480: "
                           "up to 339 images for 2 episode(s), about 7 s of rendering here (50 images/s measured)")
    assert line.endswith("with width=224 height=224")
    small = budget_message(meta, ("head",), 224, 224, horizons=[600], rate=None)
    assert small == "policy mine reads 1 camera(s) (head) at 224x224: up to 75 images for 1 episode(s)"


def test_only_the_mujoco_backend_times_the_host_renderer(tmp_path, monkeypatch, capsys) -> None:
    """The mjx backend renders on the device: a run there must not need MuJoCo's OpenGL renderer on the host (the
    GPU machine has no EGL), so its budget line gives no time; the mujoco backend's does."""
    from dojo.cli import run_cmd
    from dojo.compiler.episodes import PlannedEpisode
    from dojo.compiler.plan import compile_plan
    from dojo.compiler.spec_library import SpecLibrary

    library = SpecLibrary.load([])
    plan = compile_plan(library, library.get("task", "stack_blocks"), "standard", 0)
    plan.save(tmp_path / "plan.json")
    queue = [PlannedEpisode("stack_blocks", "generalization", "standard", 0, 0, 0, plan.hash, tmp_path / "plan.json")]
    timed = []
    monkeypatch.setattr(run_cmd, "images_per_second", lambda *args: timed.append(args) or 40.0)
    meta = PolicyMetadata(name="mine", cameras=CAMERAS, chunk_size=8)
    run_cmd._say_what_is_rendered(meta, CAMERAS, (224, 224), None, queue, set(), timed_here=False)
    assert not timed and "of rendering here" not in capsys.readouterr().err
    run_cmd._say_what_is_rendered(meta, CAMERAS, (224, 224), None, queue, set(), timed_here=True)
    assert len(timed) == 1 and "(40 images/s measured)" in capsys.readouterr().err
