"""
Split bags (pins #35): several storage files listed in metadata.yaml read as one recording.

``ros2 bag record --max-bag-duration/--max-bag-size`` writes NAME_0.mcap, NAME_1.mcap, ...
and one metadata.yaml. The same messages as one file and as 2 or 3 files must give the same
Record, array for array, and the same identification, digit for digit.
"""

from pathlib import Path
import shutil
import sys
import warnings

from io_helpers import make_record, split_bag
import numpy as np
import pytest
from rotor_id.io import bag as bag_module
from rotor_id.io.bag import BagError, BagWarning, read_record, write_record_bag

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'commands'))
from campaign_helpers import write_test_point  # noqa: E402,I100

ARRAYS = ('time_s', 't', 'rotor_speed_rad_s', 'blade_flap', 'blade_pitch')


def read_quietly(path, **kwargs):
    """read_record with its summary BagWarning caught."""
    with warnings.catch_warnings():
        warnings.simplefilter('ignore', BagWarning)
        return read_record(path, **kwargs)


def assert_identical(got, want):
    """Every array of the two Records equal, and what was said and repaired."""
    for name in ARRAYS:
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name), err_msg=name)
    assert got.blade_names == want.blade_names and got.stamp0_ns == want.stamp0_ns
    assert got.warnings == want.warnings and got.repairs == want.repairs


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
@pytest.mark.parametrize('parts', [2, 3])
def test_split_bag_reads_as_the_one_file(tmp_path, storage, parts):
    record = make_record(n=3000, seed=2)
    record.blade_flap[1700, 2] += 0.2        # a spike in the second part: repaired alike
    one = write_record_bag(tmp_path / 'one', record, storage=storage)
    split = split_bag(one, tmp_path / 'split', parts)
    assert len(list(split.glob(f'split_*.{"mcap" if storage == "mcap" else "db3"}'))) == parts
    want, got = read_quietly(one), read_quietly(split)
    assert_identical(got, want)
    assert len(got) == 3000 and [r.time_s for r in got.repairs] == [pytest.approx(1.7)]
    assert f'({parts} {storage} files)' in got.source
    # the window read (by receive time, through rosbags) crosses the files' boundaries
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(bag_module, 'WINDOW_READ_MIN_BYTES', 0)
        patch.setattr(bag_module, 'WINDOW_READ_MARGIN_S', 0.2)
        patch.setattr(bag_module, 'WINDOW_READ_CLOCK_TOLERANCE_S', 0.01)
        window = (1.2, 1.6)
        part_one = read_quietly(one, window_s=window)
        part_split = read_quietly(split, window_s=window)
    assert part_split.read_around_window and part_one.read_around_window
    assert_identical(part_split, part_one)


def test_split_bag_identifies_as_the_one_file(tmp_path):
    """A simulated test point identified from one file and from 3 files: the same estimate."""
    from rotor_id import pipeline
    from rotor_id.commands.identify import load_inputs
    one = write_test_point(tmp_path, 'one', seed=5)
    split = split_bag(one, tmp_path / 'split', 3)
    shutil.copy(tmp_path / 'one.yaml', tmp_path / 'split.yaml')
    results = []
    for bag in (one, split):
        with warnings.catch_warnings():
            warnings.simplefilter('ignore', BagWarning)
            description, record = load_inputs(bag, tmp_path / f'{bag.name}.yaml')
        results.append((record, pipeline.identify(record, description).as_json()))
    (record_one, one_json), (record_split, split_json) = results
    assert_identical(record_split, record_one)
    assert split_json['converged']
    for name, parameter in one_json['parameters'].items():
        assert split_json['parameters'][name] == parameter, name
    assert split_json['noise_std'] == one_json['noise_std']


def test_split_bag_with_a_file_missing_names_it(tmp_path):
    one = write_record_bag(tmp_path / 'one', make_record(n=600))
    split = split_bag(one, tmp_path / 'split', 3)
    (split / 'split_1.mcap').unlink()
    with pytest.raises(BagError, match=r"missing: \['split_1.mcap'\].*whole bag directory"):
        read_record(split)


def test_split_mcap_cut_short_keeps_the_other_files(tmp_path):
    """The last file of a split MCAP cut short: its readable messages and the others' kept."""
    record = make_record(n=1500, seed=3)
    one = write_record_bag(tmp_path / 'one', record)
    split = split_bag(one, tmp_path / 'split', 3)
    last = split / 'split_2.mcap'
    last.write_bytes(last.read_bytes()[:int(last.stat().st_size * 0.6)])
    with pytest.warns(BagWarning, match='damaged'):
        got = read_record(split)
    assert 1000 < len(got) < 1500
    want = record.window(0.0, got.time_s[-1])
    np.testing.assert_array_equal(got.blade_flap, want.blade_flap)
    assert any('recovered' in w for w in got.warnings)
