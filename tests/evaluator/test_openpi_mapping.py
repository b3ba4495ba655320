"""The openpi bridge's mapping file and transforms (manieval_sdk.openpi.mapping, .transform):
what a mapping file may say, what it refuses and how, and what the server gets and gives back.

Pure functions of numpy arrays, run in the service's virtualenv, which has no openpi-client
(that goes into policy images only): tests/worker/test_openpi_image.py runs the real thing.
"""

from __future__ import annotations

import textwrap
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from manieval_sdk.openpi.mapping import (
    DEFAULT_URL,
    ActionOutput,
    MappingError,
    load_mapping,
    loopback_url,
    parse_mapping,
)
from manieval_sdk.openpi.transform import (
    AnswerError,
    action_chunk,
    build_request,
    check_sources,
    image_sizes,
    prompt_text,
    resize,
    resize_with_pad,
)

REPO = Path(__file__).resolve().parents[2]
EXAMPLE = REPO / "examples" / "policies" / "openpi-server"


def mapping_file(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "mapping.toml"
    path.write_text(textwrap.dedent(text))
    return path


def rgbd_obs() -> dict[str, Any]:
    """An observation shaped as PickCube-v1's `rgbd` gives it (without the batch dimension)."""
    rng = np.random.default_rng(0)
    return {
        "agent": {"qpos": np.arange(9, dtype=np.float32), "qvel": np.zeros(9, np.float32)},
        "extra": {
            "is_grasped": np.array(True),
            "tcp_pose": np.arange(7, dtype=np.float32) / 10,
        },
        "sensor_data": {
            "base_camera": {
                "rgb": rng.integers(0, 256, (128, 128, 3), dtype=np.uint8),
                "depth": rng.integers(0, 2000, (128, 128, 1), dtype=np.int16),
            }
        },
    }


def space(obs: Any) -> Any:
    """The spec's `observation_space` for an observation: leaves are {shape, dtype}."""
    if isinstance(obs, dict):
        return {key: space(value) for key, value in obs.items()}
    return {"shape": list(obs.shape), "dtype": obs.dtype.name}


# The mapping file.


def test_the_example_mapping_reads_as_its_comments_say() -> None:
    mapping = load_mapping(EXAMPLE / "mapping.toml")
    assert mapping.server.url == "ws://127.0.0.1:8000"
    assert mapping.server.command == ("python3", "/opt/policy/serve_policy.py", "--port", "8000")
    (image,) = mapping.images
    assert image.key == ("observation/image",)
    assert image.source == ("sensor_data", "base_camera", "rgb")
    assert image.size == "image_resolution"
    assert (image.resize, image.fit, image.layout) == ("bilinear", "pad", "hwc")
    (state,) = mapping.states
    assert state.sources == (("agent", "qpos"), ("extra", "tcp_pose"))
    assert mapping.prompt is not None
    assert mapping.prompt.key == ("prompt",)
    assert mapping.actions == ActionOutput(key="actions", dims=7, horizon=None)


def test_a_mapping_of_a_prompt_alone_takes_the_defaults() -> None:
    mapping = parse_mapping({"prompt": {}})
    assert mapping.server.url == DEFAULT_URL
    assert mapping.server.command is None
    assert mapping.prompt is not None
    assert mapping.prompt.key == ("prompt",)
    assert mapping.actions == ActionOutput(key="actions", dims=None, horizon=None)


def test_commands_and_nested_keys_may_be_lists() -> None:
    mapping = parse_mapping(
        {
            "server": {"command": ["python3", "serve.py", "--name", "two words"]},
            "image": [
                {"key": ["images", "cam_high"], "source": "sensor_data/base_camera/rgb"},
                {"key": ["images", "cam_low"], "source": "sensor_data/base_camera/rgb"},
            ],
        }
    )
    assert mapping.server.command == ("python3", "serve.py", "--name", "two words")
    assert [image.key for image in mapping.images] == [
        ("images", "cam_high"),
        ("images", "cam_low"),
    ]


@pytest.mark.parametrize(
    "url",
    ["ws://127.0.0.1:8000", "ws://localhost:8000", "ws://[::1]:8000", "ws://127.0.0.2:9/path"],
)
def test_loopback_urls_are_accepted(url: str) -> None:
    assert loopback_url(url) == url


@pytest.mark.parametrize(
    ("url", "message"),
    [
        ("ws://10.0.0.1:8000", "not on the loopback interface"),
        ("ws://example.org:8000", "not on the loopback interface"),
        ("ws://0.0.0.0:8000", "not on the loopback interface"),
        ("wss://127.0.0.1:8000", "must be ws://HOST:PORT"),
        ("http://127.0.0.1:8000", "must be ws://HOST:PORT"),
        ("ws://127.0.0.1", "must be ws://HOST:PORT"),
        ("ws://127.0.0.1:99999", "must be ws://HOST:PORT"),
    ],
)
def test_other_urls_are_refused(url: str, message: str) -> None:
    with pytest.raises(MappingError, match=message):
        loopback_url(url)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("[prompt\n", "not valid TOML"),
        ("", "it maps nothing"),
        ("[promt]\n", r"the mapping has unknown field\(s\) promt"),
        ("[prompt]\ndefualt = 'x'\n", r"\[prompt\] has unknown field\(s\) defualt"),
        ("[prompt]\ndefault = 3\n", r"\[prompt\] default must be a string"),
        ("prompt = 'x'\n", "prompt must be a table"),
        ("[image]\nkey = 'a'\n", r"image must be an array of tables: write \[\[image\]\]"),
        ("[[image]]\nkey = 'a'\n", r"\[\[image\]\] #1 source: an observation path"),
        ("[[image]]\nsource = 'sensor_data/x/rgb'\n", r"\[\[image\]\] #1 key must be"),
        ("[[image]]\nkey = 'a'\nsource = 'sensor_data//rgb'\n", "an observation path"),
        ("[[image]]\nkey = 'a'\nsource = 's/rgb'\nsize = [224]\n", r"size must be \[height"),
        ("[[image]]\nkey = 'a'\nsource = 's/rgb'\nsize = [0, 9]\n", r"size must be \[height"),
        ("[[image]]\nkey = 'a'\nsource = 's/rgb'\nsize = 224\n", r"size must be \[height"),
        ("[[image]]\nkey = 'a'\nsource = 's/rgb'\nresize = 'cubic'\n", "bilinear, nearest"),
        ("[[image]]\nkey = 'a'\nsource = 's/rgb'\nlayout = 'nhwc'\n", "hwc, chw"),
        ("[[state]]\nkey = 's'\nsources = []\n", r"\[\[state\]\] #1 sources must be a non-empty"),
        ("[[state]]\nkey = 's'\nsources = ['a']\ndtype = 'int8'\n", "float32, float64"),
        (
            "[[state]]\nkey = 's'\nsources = ['a']\n[[state]]\nkey = 's'\nsources = ['b']\n",
            "the request key 's' is given more than once",
        ),
        (
            "[[state]]\nkey = 'images'\nsources = ['a']\n"
            "[[image]]\nkey = ['images', 'top']\nsource = 'c/rgb'\n",
            "the request key 'images' is given more than once",
        ),
        ("[prompt]\n[actions]\ndims = 0\n", r"\[actions\] dims must be a positive integer"),
        ("[prompt]\n[actions]\nhorizon = 2.5\n", r"\[actions\] horizon must be a positive"),
        ("[prompt]\n[actions]\nkey = ''\n", r"\[actions\] key must be a non-empty string"),
        ("[prompt]\n[server]\ncommand = 5\n", r"\[server\] command must be a string or a list"),
        ("[prompt]\n[server]\ncommand = ''\n", r"\[server\] command is empty"),
        ("[prompt]\n[server]\nstartup_timeout_s = 0\n", "startup_timeout_s must be a positive"),
        ("[prompt]\n[server]\nurl = 'ws://192.168.1.5:8000'\n", "not on the loopback"),
    ],
)
def test_a_bad_mapping_file_is_refused_with_where_and_why(
    tmp_path: Path, text: str, message: str
) -> None:
    path = mapping_file(tmp_path, text)
    with pytest.raises(MappingError, match=message) as raised:
        load_mapping(path)
    assert str(raised.value).startswith(f"{path}: ")


def test_a_missing_mapping_file_is_named(tmp_path: Path) -> None:
    with pytest.raises(MappingError, match="cannot read the mapping file"):
        load_mapping(tmp_path / "nowhere.toml")


# Images.


def test_resizing_to_the_same_size_changes_nothing() -> None:
    image = np.arange(48, dtype=np.uint8).reshape(4, 4, 3)
    assert resize(image, (4, 4)) is image


def test_nearest_halving_picks_every_second_pixel() -> None:
    image = np.arange(16, dtype=np.uint8).reshape(4, 4)
    # Pixel centres: output pixel i covers input pixels 2i and 2i + 1; its centre falls on 2i + 1.
    assert resize(image, (2, 2), "nearest").tolist() == [[5, 7], [13, 15]]


def test_bilinear_keeps_a_ramp_a_ramp_and_rounds_to_the_dtype() -> None:
    ramp = np.tile(np.arange(0, 256, 16, dtype=np.uint8), (4, 1))  # 4 x 16, 0..240 by 16
    halved = resize(ramp, (4, 8), "bilinear")
    assert halved.dtype == np.uint8
    # Centres of the output's pixels fall halfway between two input pixels.
    assert halved[0].tolist() == [8, 40, 72, 104, 136, 168, 200, 232]
    doubled = resize(ramp, (4, 32), "bilinear")
    assert doubled[0, :4].tolist() == [0, 4, 12, 20]  # the first centre lies outside: held
    assert np.all(np.diff(doubled[0].astype(int)) >= 0)


def test_resizing_keeps_channels_dtype_and_constant_images() -> None:
    for dtype, value in ((np.uint8, 200), (np.int16, -1234), (np.float32, 0.25)):
        image = np.full((128, 128, 3), value, dtype=dtype)
        for method in ("bilinear", "nearest"):
            out = resize(image, (224, 96), method)
            assert out.shape == (224, 96, 3)
            assert out.dtype == dtype
            assert np.all(out == value)


def test_a_wide_image_is_padded_centred_to_keep_its_aspect_ratio() -> None:
    image = np.full((64, 128, 3), 255, dtype=np.uint8)
    out = resize_with_pad(image, (128, 128))
    assert out.shape == (128, 128, 3)
    rows = np.nonzero(out[:, 64, 0])[0]
    assert (rows.min(), rows.max()) == (32, 95)  # 64 rows of image, 32 of zeros above and below
    assert np.all(out[:32] == 0)
    assert np.all(out[96:] == 0)


def test_a_square_image_to_a_square_size_is_not_padded() -> None:
    image = np.full((128, 128, 3), 7, dtype=np.uint8)
    assert np.all(resize_with_pad(image, (96, 96)) == 7)


# Requests.


def test_the_request_holds_resized_images_the_state_vector_and_the_prompt() -> None:
    mapping = load_mapping(EXAMPLE / "mapping.toml")
    obs = rgbd_obs()
    request = build_request(obs, mapping, sizes=[(96, 96)], prompt="pick up the red cube")
    assert sorted(request) == ["observation/image", "observation/state", "prompt"]
    image = request["observation/image"]
    assert (image.shape, image.dtype) == ((96, 96, 3), np.uint8)
    state = request["observation/state"]
    assert state.dtype == np.float32
    assert state.tolist() == [*range(9), *(np.arange(7, dtype=np.float32) / 10).tolist()]
    assert request["prompt"] == "pick up the red cube"


def test_nested_keys_chw_layout_scalars_and_depth() -> None:
    mapping = parse_mapping(
        {
            "image": [
                {
                    "key": ["images", "rgb"],
                    "source": "sensor_data/base_camera/rgb",
                    "size": [64, 32],
                    "fit": "stretch",
                    "layout": "chw",
                },
                {"key": ["images", "depth"], "source": "sensor_data/base_camera/depth"},
            ],
            "state": [{"key": "state", "sources": ["extra/is_grasped"], "dtype": "float64"}],
        }
    )
    request = build_request(rgbd_obs(), mapping, sizes=[(64, 32), None], prompt=None)
    assert request["images"]["rgb"].shape == (3, 64, 32)
    assert request["images"]["depth"].shape == (128, 128, 1)
    assert request["images"]["depth"].dtype == np.int16
    assert request["state"].tolist() == [1.0]
    assert request["state"].dtype == np.float64


def test_an_observation_without_a_mapped_entry_says_what_it_has() -> None:
    mapping = parse_mapping({"image": [{"key": "wrist", "source": "sensor_data/hand_camera/rgb"}]})
    with pytest.raises(MappingError, match=r"sensor_data has no 'hand_camera' \(it has: base_"):
        build_request(rgbd_obs(), mapping, sizes=[None], prompt=None)


def test_sources_are_checked_against_the_task_before_any_episode() -> None:
    described = space(rgbd_obs())
    check_sources(load_mapping(EXAMPLE / "mapping.toml"), described)
    state_only = {"agent": described["agent"], "extra": described["extra"]}
    with pytest.raises(MappingError, match="the observation has no 'sensor_data'"):
        check_sources(load_mapping(EXAMPLE / "mapping.toml"), state_only)
    not_an_image = parse_mapping({"image": [{"key": "i", "source": "agent/qpos"}]})
    with pytest.raises(MappingError, match=r"agent/qpos is not an image \(shape \[9\]\)"):
        check_sources(not_an_image, described)


def test_image_sizes_come_from_the_mapping_or_the_servers_metadata() -> None:
    mapping = parse_mapping(
        {
            "image": [
                {"key": "a", "source": "s/rgb", "size": "image_resolution"},
                {"key": "b", "source": "s/rgb", "size": [32, 48]},
                {"key": "c", "source": "s/rgb"},
            ]
        }
    )
    metadata = {"image_resolution": np.array([224, 224])}
    assert image_sizes(mapping, metadata) == [(224, 224), (32, 48), None]
    with pytest.raises(MappingError, match=r"does not have \(it has: action_horizon\)"):
        image_sizes(mapping, {"action_horizon": 8})
    with pytest.raises(MappingError, match=r"metadata entry 'image_resolution' must be \["):
        image_sizes(mapping, {"image_resolution": 224})


def test_the_prompt_is_the_tasks_instruction_else_the_default() -> None:
    with_default = parse_mapping({"prompt": {"default": "do the task"}})
    assert prompt_text(with_default, "push the cube to the goal") == "push the cube to the goal"
    assert prompt_text(with_default, None) == "do the task"
    assert prompt_text(parse_mapping({"state": [{"key": "s", "sources": ["a"]}]}), None) is None
    with pytest.raises(MappingError, match="the task gives no instruction"):
        prompt_text(parse_mapping({"prompt": {}}), None)


# Answers.


def test_the_servers_chunk_is_cut_to_the_action_dims_and_the_horizon() -> None:
    actions = np.arange(80, dtype=np.float64).reshape(10, 8)
    chunk = action_chunk({"actions": actions}, ActionOutput("actions", 7, 5), (7,))
    assert chunk.shape == (5, 7)
    assert chunk.dtype == np.float32
    assert chunk.tolist() == actions[:5, :7].tolist()
    assert action_chunk({"actions": actions[0, :7]}, ActionOutput("actions", None, None), (7,))[
        0
    ].tolist() == list(range(7))


@pytest.mark.parametrize(
    ("answer", "output", "message"),
    [
        ({"act": np.zeros((2, 7))}, ActionOutput("actions", None, None), r"no 'actions' \(it "),
        ("text", ActionOutput("actions", None, None), "no 'actions'"),
        ({"actions": np.zeros((4, 8))}, ActionOutput("actions", None, None), "dims = 7 to keep"),
        ({"actions": np.zeros((4, 6))}, ActionOutput("actions", None, None), "task takes 7$"),
        ({"actions": np.zeros((4, 6))}, ActionOutput("actions", 7, None), "have 6 values each"),
        ({"actions": np.zeros((1, 4, 7))}, ActionOutput("actions", None, None), r"\[H, D\]"),
        ({"actions": np.zeros((0, 7))}, ActionOutput("actions", None, None), r"\[H, D\]"),
        ({"actions": np.array(["a"] * 7)}, ActionOutput("actions", None, None), "not numbers"),
    ],
)
def test_an_answer_that_is_no_chunk_for_this_task_says_why(
    answer: Any, output: ActionOutput, message: str
) -> None:
    with pytest.raises(AnswerError, match=message):
        action_chunk(answer, output, (7,))
