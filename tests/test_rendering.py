"""The envs' renders: a walking worm visibly moves, camera and size options, the vector env's frames,
"human" mode and video recording.

The walk is the worm's suggested gait for 1 s at h = 50 ms (20 implicit steps, a few seconds). With a
following camera the tiled ground must slide by the centre of mass's displacement in pixels
(measured by cross-correlating a ground row against the first frame); with a fixed camera the ground
stays and the body's pixel centroid moves by that displacement instead.
"""

from __future__ import annotations

import sys
import types

import numpy as np
import pytest

gymnasium = pytest.importorskip("gymnasium")

from energysim.envs import CreatureEnv, CreatureVectorEnv, display  # noqa: E402
from energysim.envs.env_rendering import GRID_GAP, tile_frames  # noqa: E402
from energysim.envs.rendering import GROUND_TILE, SideViewRenderer  # noqa: E402

WALK_DT = 0.05
WALK_STEPS = 20
# a ground edge sampled at pixel centres moves in whole pixels: the measured slide is the true one
# rounded, so within 1 px
GROUND_SLIDE_TOLERANCE_PX = 1.0
# the silhouette's centroid is not the centre of mass of the bending 3D body: within 2 px (4 mm)
CENTROID_TOLERANCE_PX = 2.0


def ground_shift(reference: np.ndarray, row: np.ndarray, max_lag: int) -> int:
    """The lag in pixels (positive: `row` is `reference` moved left) of the largest normalised
    cross-correlation of two image rows `[W, 3]`."""
    a = reference.astype(np.float64).sum(axis=-1)
    b = row.astype(np.float64).sum(axis=-1)
    best, best_lag = -np.inf, 0
    for lag in range(-max_lag, max_lag + 1):
        x = a[max(0, lag) : len(a) + min(0, lag)]
        y = b[max(0, -lag) : len(b) + min(0, -lag)]
        x, y = x - x.mean(), y - y.mean()
        correlation = (x * y).sum() / np.sqrt((x * x).sum() * (y * y).sum())
        if correlation > best:
            best, best_lag = correlation, lag
    return best_lag


def body_mask(image: np.ndarray) -> np.ndarray:
    """Pixels of the body: its blue is well above its red, unlike the grey sky and the sand ground."""
    return image[..., 2].astype(int) - image[..., 0].astype(int) > 10


@pytest.fixture(scope="module")
def walk() -> dict:
    env = CreatureEnv("worm", dt=WALK_DT, render_mode="rgb_array")
    _, info = env.reset(seed=0)
    gait = env.simulation.creature.gait_action
    frames, positions, com_x = [env.render()], [], [info["x_position"]]
    split = env.simulation.scene.split_state
    positions.append(split(env.state)[0][0].numpy())
    for k in range(WALK_STEPS):
        _, _, terminated, _, info = env.step(gait(k * WALK_DT).numpy())
        assert not terminated
        frames.append(env.render())
        positions.append(split(env.state)[0][0].numpy())
        com_x.append(info["x_position"])
    mass = env.simulation.scene.vertex_mass.numpy()
    fixed = SideViewRenderer(env.simulation.creature.mesh, camera="fixed", vertex_mass=mass)
    return {
        "env": env,
        "follow": frames,
        "fixed": [fixed.render(x) for x in positions],
        "com_x": np.array(com_x),
        "scale": fixed.pixels_per_metre,
        "ground_row": fixed.ground_row,
    }


def test_following_camera_slides_the_ground_by_the_distance_walked(walk):
    frames, scale = walk["follow"], walk["scale"]
    walked_px = (walk["com_x"] - walk["com_x"][0]) * scale
    # the gait carries the worm forward several cm: more than a tile, so the ground visibly moves
    assert walked_px[-1] > 1.2 * GROUND_TILE * scale
    row = int(np.ceil(walk["ground_row"])) + 3
    for frame, expected in zip(frames, walked_px, strict=True):
        shift = ground_shift(frames[0][row], frame[row], max_lag=frame.shape[1] // 2)
        assert abs(shift - expected) <= GROUND_SLIDE_TOLERANCE_PX, (shift, expected)
    # the body itself stays centred: its centroid is the centre of mass, at the middle column
    for frame in frames:
        assert abs(np.nonzero(body_mask(frame))[1].mean() - frame.shape[1] / 2) <= CENTROID_TOLERANCE_PX


def test_fixed_camera_moves_the_body_by_the_distance_walked(walk):
    frames, scale = walk["fixed"], walk["scale"]
    walked_px = (walk["com_x"] - walk["com_x"][0]) * scale
    ground = int(np.ceil(walk["ground_row"]))
    start = np.nonzero(body_mask(frames[0]))[1].mean()
    for frame, expected in zip(frames, walked_px, strict=True):
        assert np.array_equal(frame[ground:], frames[0][ground:])  # the ground stays
        moved = np.nonzero(body_mask(frame))[1].mean() - start
        assert abs(moved - expected) <= CENTROID_TOLERANCE_PX, (moved, expected)


def test_renders_have_the_requested_size_and_camera():
    env = CreatureEnv("worm", render_mode="rgb_array", render_width=320, render_height=200, camera="fixed")
    env.reset(seed=0)
    before = env.render()
    assert before.shape == (200, 320, 3) and before.dtype == np.uint8
    scale = 320 / (3 * 0.3)  # 3 rest lengths of the 0.3 m worm across the view
    moved = env.state.clone()
    n = env.simulation.scene.num_vertices
    moved[0, : 3 * n].view(n, 3)[:, 0] += 0.03  # the whole body 3 cm forward
    env.state = moved
    after = env.render()
    shift = np.nonzero(body_mask(after))[1].mean() - np.nonzero(body_mask(before))[1].mean()
    assert abs(shift - 0.03 * scale) <= 1.0
    # a new episode takes the fixed window anew: the body is back at the centre
    env.reset(seed=0)
    assert np.array_equal(env.render(), before)
    window = CreatureEnv("worm", render_mode="rgb_array", camera="fixed", camera_window=(-0.45, 0.15))
    window.reset(seed=0)
    image = window.render()
    # the body, centred near x = 0.15 m, lies a quarter of the way across a 0.6 m window
    com_x = float(window.simulation.x_position(window.state)[0])
    expected = (com_x + 0.45) / 0.6 * 480
    assert abs(np.nonzero(body_mask(image))[1].mean() - expected) <= CENTROID_TOLERANCE_PX


def test_vector_env_renders_its_first_entry_or_a_grid():
    single = CreatureEnv("worm", render_mode="rgb_array")
    frames = []
    for seed in range(4):
        single.reset(seed=seed)
        frames.append(single.render())
    vector = CreatureVectorEnv(4, "worm", render_mode="rgb_array")
    assert vector.render() is None  # nothing to draw before reset
    vector.reset(seed=0)
    first = vector.render()
    assert first.shape == (270, 480, 3)
    # entry i is the single env reset with seed i; equal states give equal pictures, up to a pixel
    # whose centre sits on an edge
    assert (first != frames[0]).any(axis=-1).sum() <= 5
    grid_env = CreatureVectorEnv(4, "worm", render_mode="rgb_array", render_entries=4)
    grid_env.reset(seed=0)
    grid = grid_env.render()
    assert grid.shape == (2 * 270 + GRID_GAP, 2 * 480 + GRID_GAP, 3)
    corner = grid[270 + GRID_GAP :, 480 + GRID_GAP :]
    assert (corner != frames[3]).any(axis=-1).sum() <= 5


def test_tile_frames_lays_frames_row_by_row():
    frames = [np.full((3, 4, 3), value, dtype=np.uint8) for value in (10, 20, 30)]
    grid = tile_frames(frames)
    assert grid.shape == (2 * 3 + GRID_GAP, 2 * 4 + GRID_GAP, 3)
    assert (grid[:3, :4] == 10).all() and (grid[:3, 4 + GRID_GAP :] == 20).all()
    assert (grid[3 + GRID_GAP :, :4] == 30).all()
    assert tile_frames(frames[:1]) is frames[0]


def test_bad_render_options_raise_clear_errors():
    cases = [
        ({"render_mode": "ascii"}, "render_mode must be None or one of"),
        ({"render_width": 1}, "render_width must be an integer of at least 2"),
        ({"render_height": 2.5}, "render_height must be an integer"),
        ({"camera": "orbit"}, "camera must be one of"),
        ({"camera_window": (0.0, 1.0)}, "camera_window .* is for camera='fixed'"),
        ({"camera": "fixed", "camera_window": (1.0, 0.0)}, "x_max > x_min"),
        ({"camera": "fixed", "camera_window": (0.0, "far")}, "window must be a pair"),
    ]
    for options, message in cases:
        with pytest.raises(ValueError, match=message):
            CreatureEnv("worm", **options)
    with pytest.raises(ValueError, match="render_entries must be at most num_envs = 2"):
        CreatureVectorEnv(2, "worm", render_mode="rgb_array", render_entries=3)
    with pytest.raises(ValueError, match="render_entries must be an integer >= 1"):
        CreatureVectorEnv(2, "worm", render_entries=0)
    env = CreatureEnv("worm")
    renderer = SideViewRenderer(env.simulation.creature.mesh)
    with pytest.raises(ValueError, match=r"positions must have shape \[144, 3\]"):
        renderer.render(np.zeros((10, 3)))
    bad = env.simulation.creature.mesh.vertices.numpy().copy()
    bad[7, 1] = np.nan
    with pytest.raises(ValueError, match=r"vertices \[7\] are not finite"):
        renderer.render(bad)


@pytest.mark.skipif(sys.platform in ("darwin", "win32"), reason="these systems always have a display")
def test_human_mode_without_a_display_refuses_at_construction(monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    # an env checker that tries every declared mode is not offered one that cannot work here
    assert CreatureEnv("worm").metadata["render_modes"] == ["rgb_array"]
    with pytest.raises(RuntimeError, match="DISPLAY environment variable is not set.*rgb_array"):
        CreatureEnv("worm", render_mode="human")
    with pytest.raises(RuntimeError, match="DISPLAY"):
        CreatureVectorEnv(2, "worm", render_mode="human")
    # a display that does not answer: Tk's own error, named with the display
    pytest.importorskip("tkinter")
    monkeypatch.setenv("DISPLAY", ":4711")
    with pytest.raises(RuntimeError, match="could not open a window on display ':4711'"):
        CreatureEnv("worm", render_mode="human")


class _FakeTk:
    """Stands in for a Tk window: records the images shown."""

    TclError = RuntimeError

    def __init__(self) -> None:
        self.shown: list[bytes] = []
        self.updates = 0
        fake = self

        class PhotoImage:
            def __init__(self, data: bytes, format: str) -> None:
                assert format == "PPM"
                fake.shown.append(data)

        class Label:
            def __init__(self, root: object) -> None:
                pass

            def pack(self) -> None:
                pass

            def configure(self, image: object) -> None:
                pass

        class Tk:
            def title(self, text: str) -> None:
                pass

            def update_idletasks(self) -> None:
                pass

            def update(self) -> None:
                fake.updates += 1

            def destroy(self) -> None:
                pass

        self.module = types.ModuleType("tkinter")
        self.module.TclError = RuntimeError
        self.module.PhotoImage = PhotoImage
        self.module.Label = Label
        self.module.Tk = Tk


def test_human_mode_shows_every_reset_and_step_in_the_window(monkeypatch):
    fake = _FakeTk()
    monkeypatch.setattr(display, "display_problem", lambda: None)
    monkeypatch.setitem(sys.modules, "tkinter", fake.module)
    env = CreatureEnv("worm", render_mode="human", render_width=64, render_height=40)
    assert env.metadata["render_modes"] == ["human", "rgb_array"]
    reference = CreatureEnv("worm", render_mode="rgb_array", render_width=64, render_height=40)
    env.reset(seed=0)
    reference.reset(seed=0)
    action = np.full(10, 0.5)
    env.step(action)
    reference.step(action)
    assert env.render() is None  # shown, not returned
    assert len(fake.shown) == 3 and fake.updates == 3
    header = b"P6 64 40 255 "
    assert fake.shown[-1] == header + reference.render().tobytes()
    env.close()


def test_record_video_writes_every_frame(tmp_path):
    pytest.importorskip("moviepy", reason="RecordVideo needs the video extra (moviepy)")
    import imageio_ffmpeg  # moviepy's ffmpeg
    from moviepy import VideoFileClip

    env = gymnasium.make("energysim/Worm-v0", render_mode="rgb_array")
    folder = tmp_path / "videos"
    env = gymnasium.wrappers.RecordVideo(env, str(folder), episode_trigger=lambda _: True)
    env.reset(seed=0)
    steps = 11
    for _ in range(steps):
        env.step(np.zeros(10, dtype=np.float32))
    env.close()
    (video,) = folder.glob("*.mp4")
    reference = CreatureEnv("worm", render_mode="rgb_array")
    reference.reset(seed=0)
    clip = VideoFileClip(str(video))
    try:
        # the reset frame and one per step, at the env's frame rate (1/h = 60 fps); moviepy's writer
        # may leave out the last frame
        assert clip.size == [480, 270]
        assert clip.fps == pytest.approx(60)
        count, _ = imageio_ffmpeg.count_frames_and_secs(str(video))
        assert steps <= count <= steps + 1
        # the first is the reset frame, to the video codec's loss
        assert np.abs(clip.get_frame(0).astype(float) - reference.render()).mean() < 4.0
    finally:
        clip.close()
