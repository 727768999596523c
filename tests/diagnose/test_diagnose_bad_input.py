"""Bad recordings are refused before any work or allocation, with an error that names the
file and the dataset or attribute: hostile declared sizes (1e10 samples in a small file,
flags and RLE flags included) and a fuzz over malformed recordings (wrong shapes and
dtypes, NaN and Inf in every dataset, missing or broken attributes), each of which ends
in a RecordingError or in a recording the diagnosis can use, never a bare traceback.

Fast: one 72 s recording (2 detectors x 2232 samples), edited copy by copy."""

from __future__ import annotations

import json
import shutil
import tracemalloc

import h5py
import numpy as np
import pytest

from hwp_tes_systematics.diagnose import (
    RecordingError,
    read_recording,
    simulate_recording,
    write_recording,
)
from hwp_tes_systematics.diagnose.recording import _rle_segment
from hwp_tes_systematics.diagnose.recording_checks import recording_size
from hwp_tes_systematics.diagnose.testbed import A2_K, CHANNEL, MASTER_SEED, run, sky_map

HUGE = 10**10  # declared samples: 149 GiB of float64 TOD for two detectors


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    path = tmp_path_factory.mktemp("bad_input") / "base.h5"
    write_recording(path, simulate_recording(CHANNEL, 0.02, MASTER_SEED, 11, sky_map(), A2_K))
    return path


def edited(base, target, action):
    """A copy of ``base`` at ``target`` edited in place by ``action(handle)``."""
    shutil.copy(base, target)
    with h5py.File(target, "a") as handle:
        action(handle)
    return target


def replace(handle, name, data=None, **create):
    """Dataset ``name`` replaced by ``data`` (or an unwritten one: ``shape``, ``dtype``),
    keeping its attributes."""
    attrs = dict(handle[name].attrs) if name in handle else {}
    if name in handle:
        del handle[name]
    dataset = handle.create_dataset(name, data=data, **create)
    for key, value in attrs.items():
        dataset.attrs[key] = value
    return dataset


def with_value(name, where, value):
    """An edit writing ``value`` into dataset ``name`` at ``where``."""

    def action(handle):
        data = handle[name][()]
        data[where] = value
        handle[name][...] = data

    return action


def with_nan(name, where):
    return with_value(name, where, np.nan)


def with_inf(name, where):
    return with_value(name, where, np.inf)


def set_attr(key, value):
    def action(handle):
        handle["tod"].attrs[key] = value

    return action


def del_attr(key):
    def action(handle):
        del handle["tod"].attrs[key]

    return action


def detectors(edit):
    """Edit the 'detectors' attribute (a JSON list) with ``edit(list) -> new JSON text``."""

    def action(handle):
        handle["tod"].attrs["detectors"] = edit(json.loads(handle["tod"].attrs["detectors"]))

    return action


def detector_value(key, value):
    def edit(listed):
        listed[1][key] = value
        return json.dumps(listed)  # NaN and Infinity as Python's json writes them

    return detectors(edit)


def reshaped(name, function):
    return lambda handle: replace(handle, name, function(handle[name][()]))


def retyped(name, dtype):
    return lambda handle: replace(handle, name, handle[name][()].astype(dtype))


def flags(data):
    return lambda handle: replace(handle, "flags", np.asarray(data(handle["tod"].shape)))


def rle(index, data):
    return lambda handle: replace(handle, f"flags_{index:04d}", np.asarray(data))


N = 2232  # samples of the base recording (72 s at 31 Hz)

# (case, edit, what the error must name; None: the recording is read and usable)
CASES = [
    # shapes
    ("tod 1-D", reshaped("tod", lambda d: d[0]), "'tod'"),
    ("tod transposed", reshaped("tod", lambda d: d.T.copy()), "'tod'"),
    ("tod 3 detectors", reshaped("tod", lambda d: np.vstack([d, d[:1]])), "'pointings'"),
    ("pointings short", reshaped("pointings", lambda d: d[:, :-1]), "'pointings'"),
    ("pointings 2 angles", reshaped("pointings", lambda d: d[..., :2].copy()), "'pointings'"),
    ("hwp_angle 2-D", reshaped("hwp_angle", lambda d: d[None, :]), "'hwp_angle'"),
    ("hwp_angle long", reshaped("hwp_angle", lambda d: np.append(d, 0.0)), "'hwp_angle'"),
    ("tod too short", reshaped("tod", lambda d: d[:, :10].copy()), "'tod'"),
    # dtypes
    ("tod complex", retyped("tod", np.complex128), "'tod' has dtype complex128"),
    ("tod strings", retyped("tod", "S24"), "'tod' has dtype"),
    ("pointings bool", retyped("pointings", bool), "'pointings' has dtype bool"),
    ("hwp_angle complex", retyped("hwp_angle", np.complex64), "'hwp_angle' has dtype"),
    ("tod float32", retyped("tod", np.float32), None),
    # NaN (a gap: masked) and Inf (corruption: named) in every dataset
    ("tod NaN", with_nan("tod", (0, 100)), None),
    ("tod Inf", with_inf("tod", (1, 7)), "'tod'"),
    ("tod -Inf", lambda h: h["tod"].__setitem__((0, 5), -np.inf), "'tod'"),
    ("tod all NaN", with_nan("tod", ...), "no valid sample"),
    ("tod detector NaN", with_nan("tod", 1), "has no valid sample"),
    ("pointings NaN", with_nan("pointings", (1, 50, 2)), None),
    ("pointings Inf", with_inf("pointings", (0, 3, 0)), "'pointings'"),
    ("hwp_angle NaN", with_nan("hwp_angle", slice(200, 230)), None),
    ("hwp_angle Inf", with_inf("hwp_angle", 9), "'hwp_angle'"),
    ("flags float NaN", flags(lambda s: np.full(s, np.nan)), "'flags' has dtype float64"),
    ("flags wrong shape", flags(lambda s: np.zeros((s[0], s[1] + 1), bool)), "'flags'"),
    ("flags strings", flags(lambda s: np.full(s, b"x")), "'flags' has dtype"),
    ("flags all set", flags(lambda s: np.ones(s, np.uint8)), "no valid sample"),
    ("flags some", flags(lambda s: np.eye(*s, dtype=np.int32) * 7), None),
    ("RLE float NaN", rle(0, [[N * 1.0], [np.nan]]), "'flags_0000' has dtype float64"),
    ("RLE 3 rows", rle(0, np.zeros((3, 1), int)), "'flags_0000' has shape (3, 1)"),
    ("RLE 1-D", rle(1, np.zeros(4, int)), "'flags_0001' has shape"),
    ("RLE short", rle(0, [[N - 1], [0]]), "'flags_0000' decodes to 2231 samples"),
    ("RLE negative", rle(0, [[N + 5, -5], [0, 1]]), "'flags_0000' has negative run"),
    ("RLE detector 5", rle(5, [[N], [0]]), "'flags_0005' refers to detector 5"),
    ("RLE runs", rle(1, [[100, 30, N - 130], [0, 1, 0]]), None),
    # attributes
    ("no sampling rate", del_attr("sampling_rate_hz"), "'sampling_rate_hz'"),
    ("sampling rate NaN", set_attr("sampling_rate_hz", np.nan), "sampling_rate_hz = nan"),
    ("sampling rate Inf", set_attr("sampling_rate_hz", np.inf), "sampling_rate_hz = inf"),
    ("sampling rate < 0", set_attr("sampling_rate_hz", -31.0), "sampling_rate_hz = -31"),
    ("sampling rate text", set_attr("sampling_rate_hz", "fast"), "'sampling_rate_hz'"),
    ("no start time", del_attr("start_time"), "'start_time'"),
    ("start time NaN", set_attr("start_time", "nan"), "'start_time'"),
    ("start time Inf", set_attr("start_time", "inf"), "'start_time'"),
    ("start time 1e30", set_attr("start_time", "1e30"), "'start_time'"),
    ("start time scale", set_attr("start_time_scale", "martian"), "'start_time'"),
    ("start time seconds", set_attr("mjd_time", False), "mjd_time = False"),
    ("no mjd_time", del_attr("mjd_time"), None),
    ("no detectors", del_attr("detectors"), "'detectors'"),
    ("detectors not JSON", set_attr("detectors", "[{"), "'detectors' is not valid JSON"),
    ("detectors object", set_attr("detectors", "{}"), "'detectors' of dataset 'tod' is a"),
    ("detectors number", set_attr("detectors", "3"), "'detectors' of dataset 'tod' is a"),
    ("detectors strings", set_attr("detectors", '["a", "b"]'), "detector 0 of attribute"),
    ("one detector", detectors(lambda d: json.dumps(d[:1])), "'detectors' lists 1"),
    ("no angle", detectors(lambda d: json.dumps([{"name": "a"}, d[1]])), "lacks ['pol_angle"),
    ("name a number", detector_value("name", 12), "has name 12"),
    ("angle NaN", detector_value("pol_angle_rad", np.nan), "pol_angle_rad = nan"),
    ("angle text", detector_value("pol_angle_rad", "45 deg"), "pol_angle_rad = '45 deg'"),
    ("NET Inf", detector_value("net_ukrts", np.inf), "net_ukrts = inf"),
    ("alpha NaN", detector_value("alpha", np.nan), "alpha = nan"),
    ("fmin Inf", detector_value("fmin_hz", -np.inf), "fmin_hz = -inf"),
    ("NET null", detector_value("net_ukrts", None), None),
    ("angle null", detector_value("pol_angle_rad", None), "pol_angle_rad = None"),
]


def hostile_datasets(handle):
    """Every dataset declaring 1e10 samples, written only in its first 100: ~0.2 MB."""
    written = {"tod": np.s_[:, :100], "pointings": np.s_[:, :100, :], "hwp_angle": np.s_[:100]}
    for name, shape in (("tod", (2, HUGE)), ("pointings", (2, HUGE, 3)), ("hwp_angle", (HUGE,))):
        dataset = replace(handle, name, shape=shape, dtype="f8", chunks=True, compression="gzip")
        dataset[written[name]] = 0.5
    handle.create_dataset("flags", shape=(2, HUGE), dtype="u1", chunks=True, compression="gzip")
    handle.create_dataset("flags_0000", data=np.array([[HUGE], [0]]))


HOSTILE = [
    ("all datasets 1e10", hostile_datasets, "'tod' declares shape (2, 10000000000) float64"),
    (
        "pointings never written",
        lambda h: replace(h, "pointings", shape=(2, N, 3), dtype="f8", chunks=True),
        "'pointings' declares shape (2, 2232, 3) float64",
    ),
    (
        "flags 1e10",
        lambda h: h.create_dataset("flags", shape=(2, HUGE), dtype="u1", chunks=True),
        "'flags' has shape (2, 10000000000), expected (2, 2232)",
    ),
    ("RLE flags sum 1e10", rle(1, [[HUGE], [1]]), "'flags_0001' decodes to 10000000000 samples"),
    (
        "RLE flags 1e10 runs",
        lambda h: h.create_dataset("flags_0000", shape=(2, HUGE), dtype="i8", chunks=True),
        "'flags_0000' declares 10000000000 runs",
    ),
]


@pytest.mark.parametrize("case, action, named", HOSTILE, ids=[c[0] for c in HOSTILE])
def test_hostile_sizes_are_refused_before_allocation(base, tmp_path, case, action, named):
    """Declared sizes are checked before any array of that size exists: the read (and the
    segmented read of the first samples, which once made the 18.6 GiB flags array) peaks
    below 50 MB of Python/numpy allocations and ends in a RecordingError naming the file
    and the dataset."""
    path = edited(base, tmp_path / "hostile.h5", action)
    assert path.stat().st_size < 5e6
    for read in (
        lambda: recording_size(path),
        lambda: read_recording(path, memory_budget_bytes=64 * 2**30),
        lambda: read_recording(path, memory_budget_bytes=64 * 2**30, samples=(0, 64)),
    ):
        tracemalloc.start()
        try:
            with pytest.raises(RecordingError) as error:
                read()
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        assert peak < 50e6, (case, peak)
        message = str(error.value)
        assert message.startswith(f"{path}: ") and named in message, message


@pytest.mark.parametrize("case, action, named", CASES, ids=[c[0] for c in CASES])
def test_malformed_recording_is_named_or_usable(base, tmp_path, case, action, named):
    """Each malformed recording ends in a RecordingError naming the file and what is wrong
    (a dataset or attribute), or is read into a recording whose arrays are finite and
    whose bad samples are flagged; never another exception (numpy's, h5py's, json's)."""
    path = edited(base, tmp_path / "bad.h5", action)
    if named is None:
        recording = read_recording(path)
        for values in (recording.tod, recording.pointings_ecl, recording.hwp_angle_rad):
            assert np.isfinite(values).all(), case
        assert recording.flags.shape == recording.tod.shape
        assert not recording.flags.all(axis=1).any(), case
        noise = recording.nominal_noise()  # the metadata the diagnosis reads: numbers
        assert all(isinstance(v, float) for d in noise for v in d.values()), (case, noise)
        return
    with pytest.raises(RecordingError) as error:
        read_recording(path)
    message = str(error.value)
    assert message.startswith(f"{path}: "), message
    assert named in message, message


def test_read_bad_samples_are_the_edited_ones(base, tmp_path):
    """The usable cases flag what was edited, no more: a NaN TOD sample, a NaN HWP stretch
    (flagged for both detectors), flags written as integers 7, and RLE runs."""
    read = read_recording(edited(base, tmp_path / "nan.h5", with_nan("tod", (0, 100))))
    assert read.flags.sum() == 1 and read.flags[0, 100]
    read = read_recording(edited(base, tmp_path / "hwp.h5", with_nan("hwp_angle", slice(200, 230))))
    assert read.flags.sum() == 60 and read.flags[:, 200:230].all()
    some = flags(lambda s: np.eye(*s, dtype=np.int32) * 7)
    read = read_recording(edited(base, tmp_path / "flags.h5", some))
    assert read.flags.sum() == 2 and read.flags[0, 0] and read.flags[1, 1]
    runs = rle(1, [[100, 30, N - 130], [0, 1, 0]])
    read = read_recording(edited(base, tmp_path / "rle.h5", runs))
    assert read.flags.sum() == 30 and read.flags[1, 100:130].all()
    segment = read_recording(tmp_path / "rle.h5", samples=(110, 400))
    assert segment.flags.sum() == 20 and segment.flags[1, :20].all()


def test_rle_segment_equals_the_full_decoding():
    """Decoding a segment of RLE flags (a segmented read decodes no more than its samples)
    equals slicing litebird_sim's full decoding, zero-length runs and edges included."""
    from litebird_sim.compress import rle_compress, rle_decompress

    rng = np.random.default_rng(3)
    values = rng.random(500) < 0.1
    values[200:260] = True
    encoded = rle_compress(values.astype(np.int64))
    encoded = np.insert(encoded, 3, [0, 1], axis=1)  # a zero-length run
    full = rle_decompress(encoded) != 0
    np.testing.assert_array_equal(full, values)
    for start, stop in [(0, 500), (0, 1), (199, 200), (200, 261), (37, 38), (123, 499)]:
        np.testing.assert_array_equal(_rle_segment(encoded, start, stop), values[start:stop])


def test_usable_malformed_recordings_end_in_a_diagnosis(base, tmp_path):
    """The malformed recordings that are read (NaN in the TOD, the pointing and the HWP
    angle, flags and RLE flags together) are diagnosed to the end."""

    def all_at_once(handle):
        for action in (
            with_nan("tod", (0, 100)),
            with_nan("pointings", (1, 50, 2)),
            with_nan("hwp_angle", slice(200, 230)),
            flags(lambda s: np.eye(*s, dtype=np.int32) * 7),
            rle(1, [[100, 30, N - 130], [0, 1, 0]]),
        ):
            action(handle)

    recording = read_recording(edited(base, tmp_path / "nan.h5", all_at_once))
    assert recording.flags.sum() == 1 + 1 + 60 + 2 + 30
    result = run(recording, figures=False)
    assert np.isfinite(result["chi2_before"]) and np.isfinite(result["chi2_after"])


@pytest.mark.parametrize("channel", ["X9-999", "m1-140"])
def test_unknown_channel_of_a_recording_is_named_with_the_valid_ones(base, tmp_path, channel):
    """A recording whose detectors name a channel the instrument model does not know (or
    in the wrong case) is not diagnosed with A_2 = 0: the command line's nominal_a2 and
    the workflow's diagnosis stage both stop, naming the file, the value and the valid
    channels."""
    from hwp_tes_systematics.config import default_config_path, load_config
    from hwp_tes_systematics.diagnose.recording import nominal_a2
    from hwp_tes_systematics.instrument import InstrumentModelError, all_channel_names
    from hwp_tes_systematics.stages import diagnose_recordings

    def rename(listed):
        for detector in listed:
            detector["channel"] = channel
        return json.dumps(listed)

    path = edited(base, tmp_path / "renamed.h5", detectors(rename))
    recording = read_recording(path)
    with pytest.raises(RecordingError) as error:
        nominal_a2(recording, None, lambda name: pytest.fail(f"looked up {name}"))
    message = str(error.value)
    assert message.startswith(f"{path}: channel {channel!r}") and "--a2" in message
    assert all(name in message for name in all_channel_names())
    assert ("did you mean 'M1-140'?" in message) == (channel == "m1-140")

    out = tmp_path / "out"
    with pytest.raises(InstrumentModelError) as error:
        diagnose_recordings.run(
            load_config(default_config_path()),
            str(path),
            "sky.fits",
            str(out / "d.json"),
            str(out / "d.md"),
        )
    assert f"{path}: the detectors' 'channel': unknown channel {channel!r}" in str(error.value)
    assert not out.exists()


def test_the_command_line_refuses_a_hostile_recording_naming_it(base, tmp_path, capsys):
    """The command line's path (declared size, then a segmented read of the first samples
    when it would not fit): exit status 2 and the error naming the file and the dataset,
    before the sky or anything else is read."""
    import logging

    from hwp_tes_systematics import cli

    root, package = logging.getLogger(), logging.getLogger("hwp_tes_systematics")
    # main() configures logging (the root's handlers and level, the package's level)
    handlers, level, package_level = list(root.handlers), root.level, package.level

    from hwp_tes_systematics import sky

    path = edited(base, tmp_path / "hostile.h5", hostile_datasets)
    sky.write_sky_map(tmp_path / "sky.fits", np.zeros((3, 12)))  # its headers only are read
    try:
        status = cli.main(
            [
                "diagnose",
                str(path),
                "--sky",
                str(tmp_path / "sky.fits"),
                "--out",
                str(tmp_path / "o"),
            ]
        )
    finally:
        root.handlers[:] = handlers
        root.setLevel(level)
        package.setLevel(package_level)
    err = capsys.readouterr().err
    assert status == 2
    assert f"error: {path}: dataset 'tod' declares shape (2, 10000000000) float64" in err
    assert not (tmp_path / "o").exists()
