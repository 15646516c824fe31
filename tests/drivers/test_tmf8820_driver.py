"""The TMF8820 I2C driver end to end against the register-level emulator (virtual bus time)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from place_safe.drivers.tmf8820 import registers as R
from place_safe.drivers.tmf8820.bench import random_frames
from place_safe.drivers.tmf8820.emulated import EmulatedTMF8820
from place_safe.drivers.tmf8820.emulator import FAULT_KINDS, FaultPlan, TMF8820Emulator
from place_safe.drivers.tmf8820.hexfile import RamPatch, load_patch, write_patch
from place_safe.drivers.tmf8820.i2c import TMF8820Source
from place_safe.exceptions import ConfigError, SensorError, SensorTimeout

FRAMES = random_frames(40, seed=1)


@pytest.fixture
def patch_file(tmp_path):
    rng = np.random.default_rng(7)
    patch = RamPatch(0x0200, rng.integers(0, 256, 1000, dtype=np.uint8).tobytes())  # 8 chunks, the last short
    return write_patch(tmp_path / "synthetic_patch.hex", patch), patch


def _assert_exact(src: EmulatedTMF8820, frames) -> None:
    """Every delivered frame is bit-exact with the measurement the emulator presented under its ticks."""
    presented = {ticks: (ch, res) for ticks, ch, res in src.emulator.presented}
    for f in frames:
        ch, res = presented[f.extra["tmf8820"]["sys_ticks"]]
        assert f.hists.shape == (9, 128) and f.reference.shape == (128,)
        np.testing.assert_array_equal(f.hists, ch[1:])
        np.testing.assert_array_equal(f.reference, ch[0])
        np.testing.assert_array_equal(f.distances, np.asarray(res.distance_mm[:9]) / 1000.0)
        np.testing.assert_array_equal(f.confidences, res.confidence[:9])


def test_boots_rom_application_configures_and_streams_bit_exact():
    src = EmulatedTMF8820(FRAMES, record=True, driver={"period_ms": 20, "kilo_iterations": 1000})
    emu = src.emulator
    assert src.driver.identity["application"] == "ROM"
    assert src.driver.identity["app_version"] == ".".join(map(str, emu.rom_version))
    assert src.driver.identity["serial"] == f"{emu.serial:04x}"
    # the config page the device now holds is what the driver asked for
    cfg = {reg: emu._cfg(reg, n) for reg, n in ((R.CFG_PERIOD_MS, 2), (R.CFG_KILO_ITERATIONS, 2))}
    # 20 ms is shorter than a 400 kHz bus needs to read a measurement out (~94 ms of payload alone): the
    # driver lengthens the period so that measurements are not overwritten while they are read
    assert int.from_bytes(cfg[R.CFG_PERIOD_MS], "little") == src.driver.period_in_use_ms > 94
    assert int.from_bytes(cfg[R.CFG_KILO_ITERATIONS], "little") == 1000
    assert emu._cfg(R.CFG_HISTOGRAM_DUMP, 1)[0] == R.HIST_DUMP_RAW
    assert emu._cfg(R.CFG_SPAD_MAP_ID, 1)[0] == R.SPAD_MAP_3X3
    assert emu._cfg(R.CFG_ALG_SETTING, 1)[0] & R.ALG_REPORT_DISTANCES
    assert emu.active_range == R.CMD_SHORT_RANGE
    got = [src.read(1.0) for _ in range(len(FRAMES))]
    # fed in order: the i-th frame out is the i-th frame in (skipped measurements take no feed frame)
    for f, fed in zip(got, FRAMES):
        np.testing.assert_array_equal(f.hists, fed.hists)
        np.testing.assert_array_equal(f.reference, fed.reference)
        np.testing.assert_allclose(f.distances, fed.distances, atol=1e-12)
        np.testing.assert_array_equal(f.confidences, fed.confidences)
    _assert_exact(src, got)
    assert src.stats["frames"] == len(FRAMES) and src.stats["dropped_frames"] == 0
    assert int.from_bytes(emu._cfg(R.CFG_PERIOD_MS, 2), "little") == src.driver.period_in_use_ms > 94
    with pytest.raises(StopIteration):
        src.read(0.5)  # the feed has ended
    src.driver.stop()
    assert not emu.measuring
    src.close()
    src.close()  # idempotent


def test_timestamps_are_measurement_completion_times():
    src = EmulatedTMF8820(FRAMES, record=True)
    emu = src.emulator
    got = [src.read(1.0) for _ in range(30)]
    done = [(f.extra["tmf8820"]["sys_ticks"] - emu.tick_origin) * R.TICK_SECONDS for f in got]
    stamps = np.array([f.timestamp for f in got])
    assert np.all(np.diff(stamps) > 0)
    # measurement completion on the (virtual) host clock, to the poll interval plus one packet time
    np.testing.assert_allclose(stamps, done, atol=2e-3)
    assert src.clock_domain == "emulator"


def test_downloads_a_hex_patch_that_the_emulator_checks(patch_file):
    path, patch = patch_file
    assert load_patch(path) == patch
    src = EmulatedTMF8820(FRAMES, patch=patch, record=True)
    assert src.driver.identity["application"] == "RAM patch"
    assert src.driver.identity["app_version"] == ".".join(map(str, src.emulator.patch_version))
    assert bytes(src.emulator.ram[patch.address:patch.address + len(patch.data)]) == patch.data
    _assert_exact(src, [src.read(1.0) for _ in range(3)])


def test_a_wrong_patch_is_rejected_with_a_clear_error(patch_file):
    _, patch = patch_file
    wrong = RamPatch(patch.address, bytes(b ^ 1 for b in patch.data))
    emu = TMF8820Emulator(FRAMES, patch=patch)
    with pytest.raises(SensorError, match="rejected the RAM patch"):
        TMF8820Source(emu, patch=wrong, clock=emu.clock, sleep=emu.clock.sleep)


def test_bad_hex_files_give_one_line_config_errors(tmp_path):
    with pytest.raises(ConfigError, match="does not exist"):
        load_patch(tmp_path / "missing.hex")
    bad = tmp_path / "bad.hex"
    bad.write_text(":10000000ZZ\n")
    with pytest.raises(ConfigError, match="not a valid Intel HEX"):
        load_patch(bad)
    two = tmp_path / "two.hex"
    from intelhex import IntelHex

    ih = IntelHex()
    ih.puts(0x0000, b"abcd")
    ih.puts(0x1000, b"efgh")
    ih.write_hex_file(str(two))
    with pytest.raises(ConfigError, match="2 segments"):
        load_patch(two)
    good = write_patch(tmp_path / "good.hex", RamPatch(0x0200, bytes(range(64))))
    lines = good.read_text().splitlines()
    cut = tmp_path / "cut.hex"  # cut off between records: IntelHex read a shorter patch, and it was downloaded
    cut.write_text("\n".join(lines[:2]) + "\n")
    with pytest.raises(ConfigError, match="no end-of-file record"):
        load_patch(cut)
    after = tmp_path / "after.hex"  # data after the end-of-file record was dropped without a word
    after.write_text("\n".join(lines + lines[:1]) + "\n")
    with pytest.raises(ConfigError, match="1 record"):
        load_patch(after)
    assert load_patch(good).data == bytes(range(64))


@pytest.mark.parametrize("kind", FAULT_KINDS)
def test_every_fault_class_is_survived_and_counted(kind, patch_file):
    _, patch = patch_file
    # checksum faults only exist in the bootloader: arm it from the start (the patch download)
    at = 0 if kind == "checksum" else 400
    src = EmulatedTMF8820(random_frames(30, seed=2), patch=patch, record=True, faults=FaultPlan([(at, kind)], seed=3))
    got = [src.read(2.0) for _ in range(20)]
    _assert_exact(src, got)  # no half frame: everything delivered is whole and exact
    st = src.stats
    assert st["injected"][kind] == 1
    assert st[kind] == 1, f"{kind} injected once, counted {st[kind]}"
    for other in FAULT_KINDS:
        if other != kind:
            assert st[other] == 0, f"{other} counted though only {kind} was injected"
    if kind in ("short_read", "out_of_order", "missing_packet"):
        assert st["dropped_frames"] <= 1
    if kind == "reset":
        assert st["reinit"] >= 1 and src.driver.identity["application"] == "RAM patch"


def test_a_dead_bus_ends_in_a_sensor_error():
    src = EmulatedTMF8820(FRAMES, faults=FaultPlan(dead_after=500))
    with pytest.raises(SensorError, match="does not answer"):
        for _ in range(100):
            src.read(1.0)


def test_no_sensor_at_the_address():
    emu = TMF8820Emulator(FRAMES, address=0x29)
    with pytest.raises(SensorError, match="0x41 does not answer"):
        TMF8820Source(emu, clock=emu.clock, sleep=emu.clock.sleep, retries=3)


def test_timeout_when_nothing_is_measured():
    emu = TMF8820Emulator([])
    src = TMF8820Source(emu, clock=emu.clock, sleep=emu.clock.sleep)
    with pytest.raises(SensorTimeout):
        src.read(0.2)


def test_a_file_feed_without_a_readable_entry_is_a_frame_file_error(tmp_path):
    """Entries a file cannot parse are skipped; a file with none readable ended the feed as a sensor that stops does
    (the commands said "ended before its first frame", exit 1): it is a bad file, and the error says so."""
    import json

    from place_safe.exceptions import FrameFileError
    from place_safe.io.replay import FileReplaySource

    path = tmp_path / "bad.json"
    path.write_text(json.dumps([{"hists": "abc"}, {"hists": [1]}]))
    src = EmulatedTMF8820(FileReplaySource(path, realtime=False))
    with pytest.raises(FrameFileError, match=r"no readable frame in bad.json: 2 unreadable entries \(the first: "
                                             r"bad.json: frame 0: hists must hold numbers"):
        src.read(1.0)
    good = tmp_path / "mixed.json"  # one readable entry among them: it comes out, then the feed ends as before
    good.write_text(json.dumps([{"hists": "abc"}, FRAMES[0].to_dict()]))
    src = EmulatedTMF8820(FileReplaySource(good, realtime=False))
    np.testing.assert_array_equal(src.read(1.0).hists, FRAMES[0].hists)
    with pytest.raises(StopIteration):
        src.read(1.0)


def test_interrupt_line_instead_of_polling():
    emu = TMF8820Emulator(FRAMES, record=True)
    src = TMF8820Source(emu, int_line=emu.int_line, clock=emu.clock, sleep=emu.clock.sleep)
    got = [src.read(1.0) for _ in range(5)]
    for f, fed in zip(got, FRAMES):
        np.testing.assert_array_equal(f.hists, fed.hists)
    polls_per_frame = emu.stats["transfers"] / 5
    assert polls_per_frame < 80


def test_factory_calibration_is_saved_by_serial_and_loaded_at_start(tmp_path):
    src = EmulatedTMF8820(FRAMES, driver={"calibration_dir": tmp_path})
    path = src.driver.factory_calibrate()
    assert path.name == f"tmf8820-{src.emulator.serial:04x}.json"
    page = bytes(src.emulator.calibration)
    src.close()
    fresh = EmulatedTMF8820(FRAMES, driver={"calibration_dir": tmp_path})
    assert bytes(fresh.emulator.calibration) == page and any(page)
    assert fresh.driver.identity["calibration"] == str(path)
    other = EmulatedTMF8820(FRAMES, driver={"calibration_dir": tmp_path}, emulator={"serial": 0x1111})
    assert not any(other.emulator.calibration)  # another sensor's file is not used, and that is said
    assert other.driver.identity["calibration"].startswith("none: no tmf8820-1111.json in ")


def test_a_calibration_folder_that_is_a_file_is_one_line_naming_it(tmp_path):
    """``--calibration-dir FILE`` (a file, not a folder) was taken: the sensor said "none: no tmf8820-2a17.json in FILE"
    and ``--factory-calibrate`` ended "File exists: FILE", after running the sensor's calibration (round 14). The
    driver refuses it when built, naming the option's value; a folder not yet there is made by the calibration."""
    afile = tmp_path / "frames.json"
    afile.write_text("[]")
    with pytest.raises(ConfigError, match=r"factory calibration folder .*frames\.json is a file, not a folder"):
        TMF8820Source(TMF8820Emulator(FRAMES), calibration_dir=afile)
    src = EmulatedTMF8820(FRAMES, driver={"calibration_dir": tmp_path / "new"})
    assert src.driver.factory_calibrate().parent == tmp_path / "new"


def test_bad_driver_options():
    emu = TMF8820Emulator(FRAMES)
    with pytest.raises(ConfigError):
        TMF8820Source(emu, address=0x80)
    with pytest.raises(ConfigError):
        TMF8820Source(emu, kilo_iterations=0)


@pytest.mark.slow
def test_1000_frames_with_one_percent_faults_of_every_class(patch_file):
    """1 % of the frames hit by a fault, every class present; no half frame, every fault counted."""
    _, patch = patch_file
    events = []
    for j in range(10):  # 10 faults over ~1000 frames (about 63 transfers a frame)
        kind = FAULT_KINDS[j % len(FAULT_KINDS)]
        at = 3000 + j * 6000
        events += [(at, "reset"), (at + 1, "checksum")] if kind == "checksum" else [(at, kind)]
    src = EmulatedTMF8820(random_frames(64, seed=5) * 17, patch=patch, record=True, faults=FaultPlan(events, seed=9))
    got = [src.read(2.0) for _ in range(1000)]
    _assert_exact(src, got)
    ticks = [f.extra["tmf8820"]["sys_ticks"] for f in got]
    assert len(set(ticks)) == 1000 and ticks == sorted(ticks)
    st = src.stats
    assert all(st["injected"][k] >= 1 for k in FAULT_KINDS)
    for k in FAULT_KINDS:
        assert st[k] == st["injected"][k], k
    assert st["measurements"] - 1000 <= sum(st["injected"].values())


def test_a_sensor_that_keeps_resetting_ends_in_a_sensor_error():
    src = EmulatedTMF8820(FRAMES, faults=FaultPlan([(400 + 150 * i, "reset") for i in range(40)]))
    with pytest.raises(SensorError, match="keeps resetting"):
        for _ in range(30):
            src.read(1.0)


@pytest.mark.slow
@settings(max_examples=12, deadline=None)
@given(st.lists(st.tuples(st.integers(150, 2500), st.sampled_from(FAULT_KINDS)), max_size=8), st.integers(0, 99))
@example(events=[(150, "out_of_order"), (150, "missing_packet")], seed=0)
@example(events=[(289, "out_of_order"), (352, "reset")], seed=0)
@example(events=[(150, "out_of_order"), (150, "out_of_order"), (474, "short_read")], seed=52)  # cut a result's padding
# a re-read made the host late, the result frame was overwritten and the next measurement began with packet 1
@example(events=[(150, "short_read"), (826, "out_of_order"), (830, "short_read")], seed=23)
@example(events=[(150, "nak")] * 3 + [(150, "short_read"), (150, "reset"), (807, "out_of_order"),
                                      (826, "short_read")], seed=22)
# a period change's STOP wipes an unread packet 0 of a swapped pair: the swap was never shown
@example(events=[(1406, "checksum"), (1603, "short_read"), (646, "out_of_order"), (1750, "missing_packet"),
                 (1521, "out_of_order"), (1279, "short_read")], seed=59)
@example(events=[(527, "timeout"), (1208, "reset")], seed=46)  # a reset tears a read's second look
@example(events=[(1997, "short_read"), (2318, "missing_packet")], seed=90)  # the last measurement still going out
# two short reads back to back cut a header read and its second look alike: the 0xFF run is read again on its own
@example(events=[(520, "short_read"), (908, "missing_packet"), (495, "short_read")], seed=67)
def test_whatever_the_faults_frames_are_exact_or_the_source_says_why(events, seed):
    """Property: under any schedule of faults the driver hands out only whole, exact frames, or ends in a
    one-line SensorError / SensorTimeout; injected faults are all counted."""
    src = EmulatedTMF8820(random_frames(30, seed=seed), record=True, faults=FaultPlan(events, seed=seed))
    got, ended = [], None
    try:
        for _ in range(20):
            got.append(src.read(2.0))
    except (SensorError, SensorTimeout) as exc:
        assert "\n" not in str(exc)
        ended = exc
    _assert_exact(src, got)
    st_ = src.stats
    resets = st_["injected"]["reset"]
    # the measurement still going out when the reads stopped: its packet faults are counted when it closes
    pending = src.emulator.pending_faults()
    for kind in FAULT_KINDS:
        shown = st_["injected"][kind] - pending.get(kind, 0)
        if kind == "short_read":  # a reset during a read's second look tears that read as a cut would
            assert st_[kind] <= shown + resets, kind
            assert ended is not None or st_[kind] >= shown, kind
        elif ended is None and not (resets and kind in ("out_of_order", "missing_packet")):
            assert st_[kind] == shown, kind
        else:  # a reset erases the measurement in progress, and packet faults it had not shown yet with it
            assert st_[kind] <= shown, kind
    # and no fault is blamed on the host being late: a measurement is dropped as overwritten only if it was
    assert st_["overwritten"] <= src.emulator.stats["overwritten"]


def test_the_emulator_answers_smbus_byte_and_block_calls():
    emu = TMF8820Emulator(FRAMES)
    emu.write_byte_data(R.DEFAULT_ADDRESS, R.ENABLE, R.ENABLE_WAKEUP)
    emu.clock.sleep(0.01)
    assert emu.read_byte_data(R.DEFAULT_ADDRESS, R.ENABLE) == R.ENABLE_WAKEUP  # the first read is stale
    assert emu.read_byte_data(R.DEFAULT_ADDRESS, R.ENABLE) & R.ENABLE_CPU_READY
    assert emu.read_i2c_block_data(R.DEFAULT_ADDRESS, R.APPID, 1) == [R.APP_BOOTLOADER]
    body = [R.BL_SET_ADDRESS, 2, 0x00, 0x01]
    emu.write_i2c_block_data(R.DEFAULT_ADDRESS, R.CMD_STAT, body + [R.bl_checksum(body)])
    emu.clock.sleep(0.001)
    status, n, csum = emu.read_i2c_block_data(R.DEFAULT_ADDRESS, R.CMD_STAT, 3)
    assert (status, n) == (R.BL_STATUS_OK, 0) and csum == R.bl_checksum([status, n])
    with pytest.raises(ValueError):
        emu.read_i2c_block_data(R.DEFAULT_ADDRESS, R.PAGE, 33)  # SMBus blocks stop at 32 bytes
    with pytest.raises(OSError) as info:
        emu.read_byte_data(0x29, R.ENABLE)
    assert info.value.errno == R.ERRNO_NAK
