"""Hardware cameras: the OpenCV/V4L2 source reads real frames (from a video file the test writes first, which
OpenCV opens as it opens a device), a missing device or RealSense is reported by name, `backend.cameras` chooses
each camera's source and the emulator stays the default."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dojo.backends.real.cameras import CameraError, parse_sources

cv2 = pytest.importorskip("cv2")

FRAMES = 8


def _pattern(i: int, width: int = 64, height: int = 48) -> np.ndarray:
    """Frame i (RGB): a red bar whose width grows with i on a blue field, so that order is visible."""
    rgb = np.zeros((height, width, 3), np.uint8)
    rgb[:, :, 2] = 200
    rgb[:, : 6 * (i + 1), 0] = 230
    return rgb


@pytest.fixture(scope="module")
def video(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("camera") / "head.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30, (64, 48))
    assert writer.isOpened()
    for i in range(FRAMES):
        writer.write(cv2.cvtColor(_pattern(i), cv2.COLOR_RGB2BGR))
    writer.release()
    return path


def test_the_opencv_source_reads_the_frames_in_order_as_rgb(video) -> None:
    from dojo.backends.real.opencv_cameras import STALL_READS, OpenCVCamera

    camera = OpenCVCamera("head", str(video), 64, 48)
    try:
        seen = [camera._last] + [camera.frames()["head"] for _ in range(FRAMES - 1)]
        for i, frame in enumerate(seen):
            assert frame.shape == (48, 64, 3) and frame.dtype == np.uint8
            assert np.abs(frame.astype(int) - _pattern(i)).mean() < 6, f"frame {i}"  # MJPEG is lossy
        assert camera.dropped == 0
        repeated = camera.frames()["head"]  # the stream ended: the last frame again, counted
        assert np.array_equal(repeated, seen[-1]) and camera.dropped == 1
        with pytest.raises(CameraError, match=r"camera 'head' \(OpenCV device .*head\.avi'\) delivered no new frame"):
            for _ in range(STALL_READS):
                camera.frames()
    finally:
        camera.close()


def test_the_opencv_source_resizes_to_the_size_asked_for(video) -> None:
    from dojo.backends.real.opencv_cameras import OpenCVCamera

    camera = OpenCVCamera("left_wrist", str(video), 32, 24)
    try:
        frame = camera.frames()["left_wrist"]
        assert frame.shape == (24, 32, 3)
        assert np.abs(frame.astype(int) - cv2.resize(_pattern(1), (32, 24), interpolation=cv2.INTER_AREA)).mean() < 6
    finally:
        camera.close()


@pytest.mark.parametrize("device", ["/dev/video97", "97"])
def test_a_missing_usb_camera_is_reported_with_its_name_and_device(device) -> None:
    from dojo.backends.real.opencv_cameras import OpenCVCamera

    with pytest.raises(CameraError, match=rf"camera 'right_wrist' \(OpenCV device '{device}'\): cannot open it"):
        OpenCVCamera("right_wrist", device, 640, 480)


def test_a_missing_realsense_is_reported_not_a_crash() -> None:
    """A real `rs.context().query_devices()` call: with no RealSense attached the camera says so by name."""
    rs = pytest.importorskip("pyrealsense2")
    from dojo.backends.real.realsense_cameras import RealSenseCamera

    connected = [d.get_info(rs.camera_info.serial_number) for d in rs.context().query_devices()]
    with pytest.raises(CameraError, match=r"camera 'head' \(RealSense serial '000000000000'\): not found; "
                                          r"RealSense devices connected: "):
        RealSenseCamera("head", "000000000000", 640, 480)
    if not connected:
        with pytest.raises(CameraError, match=r"camera 'head' \(RealSense device\): not found; .*connected: none"):
            RealSenseCamera("head", "", 640, 480)


def test_realsense_depth_is_aligned_to_colour_in_millimetres_as_the_simulator_gives_it() -> None:
    """A synthetic frameset through the SDK's own path (a `software_device` with a Z16 depth and an RGB8 colour
    stream, a D405's 0.1 mm depth units, frames matched by `rs.syncer`) into the camera's frame reader: the depth
    comes aligned to colour as `<camera>_depth`, uint16 millimetres like the simulator's, 0 kept as no depth."""
    rs = pytest.importorskip("pyrealsense2")
    from dojo.backends.real.realsense_cameras import DepthToColour, camera_frames

    width, height, units = 64, 48, 0.0001
    device = rs.software_device()
    sensors = {"depth": device.add_sensor("Depth"), "color": device.add_sensor("Color")}
    intrinsics = rs.intrinsics()
    intrinsics.width, intrinsics.height, intrinsics.ppx, intrinsics.ppy = width, height, width / 2, height / 2
    intrinsics.fx = intrinsics.fy = 50.0
    intrinsics.model, intrinsics.coeffs = rs.distortion.none, [0.0] * 5
    profiles = {}
    for uid, (kind, fmt, bpp) in enumerate((("depth", rs.format.z16, 2), ("color", rs.format.rgb8, 3))):
        stream = rs.video_stream()
        stream.type, stream.index, stream.uid, stream.fps = getattr(rs.stream, kind), 0, uid, 30
        stream.width, stream.height, stream.bpp, stream.fmt, stream.intrinsics = width, height, bpp, fmt, intrinsics
        profiles[kind] = sensors[kind].add_video_stream(stream)
    sensors["depth"].add_read_only_option(rs.option.depth_units, units)
    same_place = rs.extrinsics()
    same_place.rotation, same_place.translation = [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0], [0.0, 0.0, 0.0]
    profiles["depth"].register_extrinsics_to(profiles["color"], same_place)
    device.create_matcher(rs.matchers.dlr_c)
    syncer = rs.syncer()
    for kind in ("depth", "color"):
        sensors[kind].open(profiles[kind])
        sensors[kind].start(syncer)
    raw = np.tile(np.arange(width, dtype=np.uint16) * 100 + 5000, (height, 1))  # 500.0 .. 1130.0 mm
    raw[:4, :4] = 0
    colour = np.zeros((height, width, 3), np.uint8)
    colour[..., 1] = 200
    for number in range(1, 3):  # the syncer hands on a matched pair once the next frames arrive
        for kind, pixels, bpp in (("depth", raw, 2), ("color", colour, 3)):
            frame = rs.software_video_frame()
            frame.pixels, frame.bpp, frame.stride = pixels, bpp, width * bpp
            frame.timestamp, frame.frame_number, frame.domain = number * 33.3, number, rs.timestamp_domain.hardware_clock
            frame.profile = profiles[kind].as_video_stream_profile()
            sensors[kind].on_video_frame(frame)
    frameset = syncer.wait_for_frames(5000)
    while frameset.size() < 2:
        frameset = syncer.wait_for_frames(5000)
    scale = sensors["depth"].get_option(rs.option.depth_units)  # what get_depth_scale() reads on a device
    frames = camera_frames("head", frameset, DepthToColour(scale))
    assert set(frames) == {"head", "head_depth"}
    depth = frames["head_depth"]
    assert depth.dtype == np.uint16 and depth.shape == (height, width)
    seen = depth > 0  # alignment reprojects every pixel: a few at the image's edge are left without depth
    assert seen.mean() > 0.9 and not seen[:4, :4].any()
    assert np.array_equal(depth[seen], raw[seen] // 10)  # 0.1 mm units -> mm, pixel for pixel
    assert frames["head"].shape == (height, width, 3) and (frames["head"][..., 1] == 200).all()
    for sensor in sensors.values():
        sensor.stop()
        sensor.close()


def test_depth_from_a_usb_camera_is_refused_and_a_missing_depth_realsense_is_named() -> None:
    from dojo.backends.real.cameras import open_cameras

    with pytest.raises(CameraError, match=r"cameras \['left_wrist'\]: USB cameras \(opencv\) give RGB only"):
        open_cameras({"left_wrist": ("opencv", "0")}, 640, 480, True, None)
    pytest.importorskip("pyrealsense2")
    with pytest.raises(CameraError, match=r"camera 'head' \(RealSense serial '000000000000'\): not found"):
        open_cameras({"head": ("realsense", "000000000000")}, 640, 480, True, None)


def test_backend_cameras_chooses_each_cameras_source_and_the_emulator_is_the_default() -> None:
    names = ("head", "left_wrist", "right_wrist")
    assert parse_sources("emulator", names) == dict.fromkeys(names, ("emulator", ""))
    assert parse_sources({"head": "realsense:123", "left_wrist": "opencv:/dev/video2"}, names) == {
        "head": ("realsense", "123"), "left_wrist": ("opencv", "/dev/video2"), "right_wrist": ("emulator", "")}
    with pytest.raises(ValueError, match=r"backend.cameras.head: 'usb:0' is not a camera source"):
        parse_sources({"head": "usb:0"}, names)
    assert parse_sources({"top": "opencv:0"}, names) == dict.fromkeys(names, ("emulator", ""))  # not filmed
    with pytest.raises(ValueError, match=r"backend.cameras: expected 'emulator' or a map"):
        parse_sources("opencv:0", names)


def test_the_real_backend_films_with_the_usb_source_and_hardware_needs_every_camera_named(video) -> None:
    pytest.importorskip("can")
    pytest.importorskip("piper_sdk")
    from dojo.backends.real import make
    from dojo.backends.registry import BackendOptions
    from dojo.compiler.plan import compile_plan
    from dojo.compiler.spec_library import SpecLibrary

    library = SpecLibrary.load([Path(__file__).parent / "pack"], strict=False)
    plan = compile_plan(library, library.get("task", "piper_block_probe"), "standard", 0)
    options = BackendOptions(cameras=("head", "left_wrist"), width=64, height=48,
                             settings={"driver": "emulator", "cameras": {"left_wrist": f"opencv:{video}"}})
    with make(options) as real:
        real.load([plan])
        images = real.reset()[0]["images"]
        assert np.abs(images["left_wrist"].astype(int) - _pattern(1)).mean() < 6  # the file's frames
        assert images["head"].any() and np.abs(images["head"].astype(int) - _pattern(1)).mean() > 20  # rendered
    hardware = make(BackendOptions(cameras=("head",), width=64, height=48,
                                   settings={"driver": "piper", "can": ["dojo_absent_l", "dojo_absent_r"]}))
    with pytest.raises(CameraError, match=r"cameras \['head'\] have no hardware source: name each in "
                                          r"backend.cameras"):
        hardware.load([plan])
    hardware.close()
