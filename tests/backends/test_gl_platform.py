"""The OpenGL platform is probed before MuJoCo is imported: a GPU server without libEGL must still run physics."""

import pytest

from dojo.backends import gl_platform as G


@pytest.fixture
def clean_env(monkeypatch):
    for var in ("MUJOCO_GL", "PYOPENGL_PLATFORM", "DOJO_GL_REASON"):
        monkeypatch.delenv(var, raising=False)
    return monkeypatch


def test_egl_first_when_its_library_loads(clean_env):
    assert G.choose_gl_platform(lambda p: True) == "egl"
    assert G.os.environ["MUJOCO_GL"] == "egl" and G.os.environ["PYOPENGL_PLATFORM"] == "egl"
    assert G.gl_enabled()


def test_osmesa_when_only_osmesa_loads(clean_env):
    assert G.choose_gl_platform(lambda p: p == "osmesa") == "osmesa"
    assert G.os.environ["PYOPENGL_PLATFORM"] == "osmesa"


def test_disabled_with_a_reason_when_nothing_loads(clean_env):
    """What the H100 machine looks like: libEGL_nvidia but no libEGL.so.1 loader, no OSMesa."""
    assert G.choose_gl_platform(lambda p: False) == "disable"
    assert not G.gl_enabled()
    assert "PYOPENGL_PLATFORM" not in G.os.environ
    reason = G.gl_unavailable_reason()
    assert "libEGL.so.1" in reason and "libegl1" in reason


def test_the_users_choice_is_kept_and_not_probed(clean_env):
    clean_env.setenv("MUJOCO_GL", "osmesa")

    def probe(platform):
        raise AssertionError("probed although the user chose")

    assert G.choose_gl_platform(probe) == "osmesa"
    assert "set by the user" in G.gl_unavailable_reason()


def test_the_real_probe_answers_without_raising():
    assert isinstance(G.library_loads("egl"), bool)
    assert isinstance(G.library_loads("osmesa"), bool)


def test_renderer_refuses_clearly_without_gl(clean_env):
    from dojo.backends.mujoco.render import open_renderer

    clean_env.setenv("MUJOCO_GL", "disable")
    with pytest.raises(RuntimeError, match="OpenGL renderer is disabled"):
        open_renderer(None, 8, 8)
