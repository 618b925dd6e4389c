# Copyright 2026 reduced_dynamics developers
#
# Licensed under the Apache License, Version 2.0 (the "License");
# you may not use this file except in compliance with the License.
# You may obtain a copy of the License at
#
#     http://www.apache.org/licenses/LICENSE-2.0
#
# Unless required by applicable law or agreed to in writing, software
# distributed under the License is distributed on an "AS IS" BASIS,
# WITHOUT WARRANTIES OR CONDITIONS OF ANY KIND, either express or implied.
# See the License for the specific language governing permissions and
# limitations under the License.

"""replay-many: bags found, per-bag outputs, the table, failures, resuming, backends."""

from __future__ import annotations

import itertools
import json
import os
from pathlib import Path
import shutil

import numpy as np
import pytest

from reduced_dynamics.bag.reader import open_bag
from reduced_dynamics.bag.writer import BagWriter
from reduced_dynamics.cli import main
from reduced_dynamics.command_mapping import CommandMapping, freeflyer2_mapping
from reduced_dynamics.fleet import (find_bags, plan_jobs, plot_fleet, read_table, run_bag,
                                    run_fleet)
from reduced_dynamics.messages import cdr
from reduced_dynamics.resources import config_path
from reduced_dynamics.thrust_correlation import thrust_correlation
from reduced_dynamics.thrusters import FREEFLYER_ARM, FREEFLYER_FORCE, LAYOUTS

DATA = Path(__file__).resolve().parent / 'data'
FREEFLYER_URDF = str(config_path('robots/freeflyer.urdf'))
#: Summary entries that are wall-clock times or paths, not results.
_NOT_RESULTS = {'seconds', 'samples_per_second', 'input_bag', 'output_bag', 'wall_s',
                'worker_peak_rss_mib'}


def _manifest(tmp_path: Path, extra: str = '') -> Path:
    """Return a manifest giving the freeflyer bags their robot and base topic."""
    path = tmp_path / 'manifest.yaml'
    path.write_text(f"""
bags:
  - path: {DATA / 'freeflyer_testbed'}
    urdf: {FREEFLYER_URDF}
    base_pose_topic: /base_pose
  - path: {DATA / 'paper_constant'}
  - path: {DATA / 'planar_pose_only'}
    urdf: {config_path('robots/planar_testbed.urdf')}
    base_joint: planar
{extra}""")
    return path


def _results(summary: dict) -> dict:
    """Return a summary without its timings and paths (what must not depend on the run)."""
    fleet = {k: v for k, v in summary.pop('fleet').items() if k not in _NOT_RESULTS}
    return {**{k: v for k, v in summary.items() if k not in _NOT_RESULTS}, 'fleet': fleet}


def _outputs(out_dir: Path) -> dict:
    """Return every bag's summary results and output bag bytes under a fleet's OUTDIR."""
    found = {}
    for summary in sorted(out_dir.glob('*/summary.json')):
        bag = summary.parent / 'bag'
        found[summary.parent.name] = (
            _results(json.loads(summary.read_text())),
            {f.name: f.read_bytes() for f in sorted(bag.iterdir())})
    return found


def test_a_directory_expands_to_the_rosbag2_bags_under_it(tmp_path):
    campaign = tmp_path / 'campaign'
    shutil.copytree(DATA / 'paper_constant', campaign / 'day1' / 'run_a')
    shutil.copytree(DATA / 'planar_pose_only', campaign / 'day2' / 'run_b')
    shutil.copy(DATA / 'paper_constant' / 'paper_constant.mcap', campaign / 'loose.mcap')
    (campaign / 'notes.txt').write_text('not a bag')
    assert find_bags(campaign) == [campaign / 'day1' / 'run_a', campaign / 'day2' / 'run_b',
                                   campaign / 'loose.mcap']
    # A bag's own .mcap is not a second bag, and a bag given itself is one bag.
    assert find_bags(campaign / 'day1' / 'run_a') == [campaign / 'day1' / 'run_a']
    with pytest.raises(FileNotFoundError, match='no such bag'):
        find_bags(tmp_path / 'missing')


def test_fleet_outputs_table_and_damaged_bags(tmp_path):
    """One row per bag; an unreadable bag is a failed row, the exit status counts it."""
    broken = tmp_path / 'broken'
    broken.mkdir()
    (broken / 'metadata.yaml').write_text('not: [a, rosbag2, metadata')
    truncated = tmp_path / 'truncated.mcap'
    data = (DATA / 'paper_constant' / 'paper_constant.mcap').read_bytes()
    truncated.write_bytes(data[:len(data) // 2])
    out = tmp_path / 'out'
    status = main(['replay-many', str(broken), str(truncated), '--manifest',
                   str(_manifest(tmp_path)), '-o', str(out), '--workers', '2', '--quiet'])
    assert status == 1
    rows = {row['name']: row for row in read_table(str(out / 'fleet.parquet'))}
    assert read_table(str(out / 'fleet.csv'))[0]['name'] == 'broken'
    assert set(rows) == {'broken', 'truncated', 'freeflyer_testbed', 'paper_constant',
                         'planar_pose_only'}
    assert rows['broken']['status'] == 'failed' and 'broken' in rows['broken']['error']
    assert rows['truncated']['status'] == 'damaged' and rows['truncated']['damaged']
    assert rows['truncated']['damage_regions'] > 0 and rows['truncated']['bytes_lost'] > 0
    good = rows['freeflyer_testbed']
    summary = json.loads((out / 'freeflyer_testbed' / 'summary.json').read_text())
    assert good['status'] == 'ok' and good['robot'] == 'freeflyer'
    assert good['inputs_received'] == sum(summary['messages_in'].values()) == 1792
    assert good['processed'] == summary['processed']
    assert good['events'] == len(summary['events'])
    assert good['mu_spread_max'] == max(summary['mu_spread'])
    assert good['filter_poses_retimed'] == summary['filter']['poses_retimed']
    assert good['duration_s'] == pytest.approx(15.003393865)
    assert good['wall_s'] > 0 and good['worker_peak_rss_mib'] > 10
    with open_bag(out / good['output_bag']) as reader:
        assert reader.message_count() == sum(summary['messages_out'].values()) > 0
    # The planar testbed with its own robot: per-bag options from the manifest.
    assert rows['planar_pose_only']['robot'] == 'planar_testbed'
    assert rows['planar_pose_only']['processed'] > 0
    assert rows['paper_constant']['robot'] == 'paper_robot'


def test_resume_skips_bags_whose_options_hash_matches(tmp_path):
    out = tmp_path / 'out'
    args = ['replay-many', str(DATA / 'paper_constant'), str(DATA / 'paper_thruster'),
            '-o', str(out), '--workers', '1', '--quiet']
    assert main(args) == 0
    first = {p: p.stat().st_mtime_ns for p in out.glob('*/bag/*')}
    assert main(args) == 0
    assert {p: p.stat().st_mtime_ns for p in out.glob('*/bag/*')} == first
    whole = read_table(str(out / 'fleet.csv'))
    assert all(row['resumed'] for row in whole)
    # Other options: replayed again, the new window in the table.
    assert main(args + ['--end', '2.0']) == 0
    rows = read_table(str(out / 'fleet.parquet'))
    assert not any(row['resumed'] for row in rows)
    assert [row['window_end_s'] for row in rows] == [2.0, 2.0]
    assert all(0 < row['processed'] < full['processed'] for row, full in zip(rows, whole))


def test_manifest_refuses_unknown_options(tmp_path, capsys):
    manifest = tmp_path / 'm.yaml'
    manifest.write_text(f'bags:\n  - path: {DATA / "paper_constant"}\n    strat: 2\n')
    assert main(['replay-many', '--manifest', str(manifest), '-o', str(tmp_path / 'o')]) == 2
    assert "unknown options ['strat']" in capsys.readouterr().err


def test_manifest_options_apply_per_bag_over_the_command_line(tmp_path):
    manifest = _manifest(tmp_path, f'  - path: {DATA / "paper_constant"}\n    start: 1.0\n')
    jobs = {job.name: job for job in plan_jobs([str(DATA)], str(tmp_path / 'o'),
                                               {'end': 2.5, 'urdf': None}, str(manifest))}
    # every rosbag2 bag under test/data (a folder with metadata.yaml, nested ones too)
    assert len(jobs) == len(list(DATA.rglob('metadata.yaml')))
    assert jobs['paper_constant'].options == {'end': 2.5, 'start': 1.0}
    assert jobs['freeflyer_testbed'].options['urdf'] == FREEFLYER_URDF
    assert jobs['paper_realistic'].options == {'end': 2.5}
    assert len({job.options_hash for job in jobs.values()}) == len(jobs)


def test_a_named_manifest_entry_is_a_job_of_its_own(tmp_path):
    """The same bag whole and as a time window: two jobs, two rows."""
    manifest = tmp_path / 'm.yaml'
    manifest.write_text(f"""
defaults: {{end: 3.0}}
bags:
  - {DATA / 'paper_constant'}
  - {{path: {DATA / 'paper_constant'}, name: first-second, end: 1.0, plots: true}}
""")
    out = tmp_path / 'out'
    assert main(['replay-many', '--manifest', str(manifest), '-o', str(out), '--quiet',
                 '--workers', '1']) == 0
    rows = read_table(str(out / 'fleet.csv'))
    assert [(r['name'], r['window_end_s']) for r in rows] == [('paper_constant', 3.0),
                                                              ('first-second', 1.0)]
    assert 0 < rows[1]['processed'] < rows[0]['processed']
    assert (out / 'first-second' / 'plots' / 'momentum.png').is_file()
    assert not (out / 'paper_constant' / 'plots').exists()
    manifest.write_text(f'bags:\n  - {{path: {DATA}, name: all}}\n')
    with pytest.raises(ValueError, match='an entry with a name is one bag'):
        plan_jobs([], str(out), {}, str(manifest))


# --- command mapping ---------------------------------------------------------------------

def test_freeflyer2_mapping_is_the_data_readme_switch_table():
    mapping = freeflyer2_mapping()
    assert mapping.topic == '/robot/commands/binary_thrust' and len(mapping.thrusters) == 8
    np.testing.assert_allclose(mapping.units, np.array(LAYOUTS['freeflyer']) * FREEFLYER_FORCE,
                               atol=1e-15)
    for switches in itertools.product((0, 1), repeat=8):
        s = switches
        wrench = mapping.wrench(s)
        # Fx = s2 + s5 - s1 - s6, Fy = s4 + s7 - s0 - s3,
        # Mz / arm = s1 + s3 + s5 + s7 - s0 - s2 - s4 - s6 (0.2 N each).
        assert wrench[0] == pytest.approx(FREEFLYER_FORCE * (s[2] + s[5] - s[1] - s[6]))
        assert wrench[1] == pytest.approx(FREEFLYER_FORCE * (s[4] + s[7] - s[0] - s[3]))
        assert wrench[5] == pytest.approx(FREEFLYER_FORCE * FREEFLYER_ARM * (
            s[1] + s[3] + s[5] + s[7] - s[0] - s[2] - s[4] - s[6]))


@pytest.mark.parametrize('change, message', [
    ({'thrusters': []}, 'non-empty "thrusters"'),
    ({'command': {'topic': '/c', 'type': 'a/msg/B'}}, 'command needs field'),
    ({'thrusters': [{'direction': [0, 0, 0], 'position': [0, 0, 0], 'force': 1}]},
     'direction must not be zero'),
    ({'thrusters': [{'direction': [1, 0], 'position': [0, 0, 0], 'force': 1}]},
     'direction must be 3 numbers'),
    ({'thrusters': [{'direction': [1, 0, 0], 'position': [0, 0, 0], 'force': -1}]},
     'force must be finite and > 0'),
    ({'thrusters': [{'direction': [1, 0, 0], 'position': [0, 0, 0], 'force': 1, 'isp': 3}]},
     "unknown keys \\['isp'\\]"),
])
def test_command_mapping_refuses_bad_yaml_with_a_message(change, message):
    data = {'command': {'topic': '/c', 'type': 'a/msg/B', 'field': 'v'},
            'thrusters': [{'direction': [1, 0, 0], 'position': [0, 0.5, 0], 'force': 2}]}
    CommandMapping.from_mapping(data)
    with pytest.raises(ValueError, match=message):
        CommandMapping.from_mapping({**data, **change})


def test_a_mapping_gives_any_thruster_layout_its_wrench():
    """A throttled (float) thruster off the axis: force and moment r x f by the YAML."""
    mapping = CommandMapping.from_mapping({
        'command': {'topic': 'cmd', 'type': 'a/msg/B', 'field': 'throttle'},
        'thrusters': [{'direction': [0, 0, 2], 'position': [0.5, 0, 0], 'force': 4},
                      {'direction': [1, 0, 0], 'position': [0, 0.25, 0], 'force': 1}]})
    assert mapping.topic == '/cmd'
    np.testing.assert_allclose(mapping.wrench([0.5, 1.0]), [1, 0, 2, 0, -1, -0.25])


def with_thruster_commands(source: Path, out: Path, mapping: CommandMapping) -> int:
    """
    Copy ``source``'s poses and write its commanded wrenches as switch messages.

    Each WrenchStamped on /commanded_wrench becomes the mapping's command message
    (same record time and stamp) whose switches give that wrench.
    """
    store = mapping.typestore()
    patterns = list(itertools.product((False, True), repeat=len(mapping.thrusters)))
    wrenches = np.array([mapping.wrench(p) for p in patterns])
    msgtypes = {'/base_pose': 'geometry_msgs/msg/PoseStamped', mapping.topic: mapping.msgtype}
    count = 0
    with open_bag(source) as reader, BagWriter(out, msgtypes, typestore=store) as writer:
        for message in reader.raw_messages(['/base_pose', '/commanded_wrench']):
            if message.topic == '/base_pose':
                writer.write_raw('/base_pose', message.timestamp_ns, bytes(message.data))
                continue
            command = cdr.decode_wrench_stamped(bytes(message.data))
            wanted = np.concatenate([command.force, command.torque])
            best = int(np.argmin(np.abs(wrenches - wanted).sum(axis=1)))
            assert np.allclose(wrenches[best], wanted, atol=1e-9)
            header = store.types['std_msgs/msg/Header'](
                store.types['builtin_interfaces/msg/Time'](
                    command.stamp_ns // 10**9, command.stamp_ns % 10**9), 'robot')
            msg = store.types[mapping.msgtype](header, np.array(patterns[best]))
            writer.write(mapping.topic, message.timestamp_ns, msg)
            count += 1
    return count


def test_correlation_columns_from_a_command_mapping(tmp_path):
    """The simulated testbed's commands as freeflyer2 switch messages: the table's figures."""
    mapping_path = str(config_path('thrusters/freeflyer2.yaml'))
    mapping = CommandMapping.load(mapping_path)
    bags = tmp_path / 'bags'
    bags.mkdir()
    assert with_thruster_commands(DATA / 'freeflyer_testbed', bags / 'testbed', mapping) == 122
    # the same robot's recording without the thruster command topic
    shutil.copytree(DATA / 'freeflyer_testbed', bags / 'no_commands')
    out = tmp_path / 'out'
    assert main(['replay-many', str(bags), '-o', str(out), '--urdf', FREEFLYER_URDF,
                 '--base-pose-topic', '/base_pose', '--command-mapping', mapping_path,
                 '--workers', '1', '--quiet']) == 0
    rows = {row['name']: row for row in read_table(str(out / 'fleet.parquet'))}
    # A bag without commands is replayed; its correlation columns say why they are empty.
    assert rows['no_commands']['status'] == 'ok' and rows['no_commands']['corr_fx'] is None
    assert 'no command topic /robot/commands/binary_thrust' in rows['no_commands']['corr_error']
    row = rows['testbed']
    assert row['status'] == 'ok' and row['corr_error'] is None
    expected = thrust_correlation(str(bags / 'testbed'), str(out / 'testbed' / 'bag'),
                                  pose_topic='/base_pose', mapping=mapping)
    assert (row['corr_fx'], row['corr_fy'], row['corr_mz'], row['corr_samples']) == expected
    # Measured: 0.995 / 0.994 / 0.994 (smoothed, the default; causal 0.90 / 0.88 / 0.84).
    assert min(expected[:3]) > 0.98
    png = plot_fleet(str(out / 'fleet.parquet'), str(tmp_path / 'fleet.png'))
    assert os.path.getsize(png) > 1000


# --- backends -------------------------------------------------------------------------------

def _compare(reference: dict, outputs: dict, what: str) -> None:
    """Assert equal summaries (timings and paths aside) and byte-equal output bags."""
    assert outputs.keys() == reference.keys() and len(outputs) == 3
    for name in outputs:
        assert outputs[name][0] == reference[name][0], (what, name)
        assert outputs[name][1] == reference[name][1], (what, name)


def _fleet(tmp_path: Path, manifest: str, backend: str, workers: int) -> dict:
    out = tmp_path / f'{backend}{workers}'
    result = run_fleet(plan_jobs([], str(out), {}, manifest), str(out), workers, backend,
                       progress=False)
    assert [row['status'] for row in result.rows] == ['ok'] * 3, result.rows
    return _outputs(out)


def test_local_pool_and_dask_give_identical_outputs_whatever_the_workers(tmp_path):
    """Three shipped bags: 1 and 2 local workers, 2 Dask workers (a LocalCluster here)."""
    manifest = str(_manifest(tmp_path))
    reference = _fleet(tmp_path, manifest, 'local', 1)
    _compare(reference, _fleet(tmp_path, manifest, 'local', 2), 'local 2')
    pytest.importorskip('distributed', reason='dask distributed is not installed '
                                              '(pip install .[fleet])')
    _compare(reference, _fleet(tmp_path, manifest, 'dask', 2), 'dask 2')


#: The tests on a local Ray cluster run in one pytest-xdist worker, one after the other.
ONE_RAY_CLUSTER = pytest.mark.xdist_group('ray_cluster')


@pytest.fixture(scope='class')
def ray():
    """
    Return the ray module with a local cluster of 2 CPUs running (shut down after the class).

    Skipped, with the reason, only where Ray is not installed or cannot start. One cluster
    for the class's tests: a start and a shutdown cost ~16 s of CPU here (measured).
    """
    ray = pytest.importorskip('ray', reason='ray is not installed (pip install .[fleet])')
    try:
        ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    except Exception as error:  # noqa: B902 (whatever stops Ray is the reason to skip)
        pytest.skip(f'a local Ray cluster cannot start on this machine: {error}')
    yield ray
    ray.shutdown()


@ONE_RAY_CLUSTER
class TestOnALocalRayCluster:
    """Tests on one local Ray cluster (``ray.init()`` on this machine), started once for them."""

    def test_ray_local_cluster_replays_three_shipped_bags_identically(self, tmp_path, ray):
        """Three shipped bags on the local Ray cluster: the local pool's outputs."""
        manifest = str(_manifest(tmp_path))
        reference = _fleet(tmp_path, manifest, 'local', 1)
        assert ray.cluster_resources().get('CPU') == 2
        _compare(reference, _fleet(tmp_path, manifest, 'ray', 2), 'ray 2')
        assert ray.is_initialized()  # replay-many left the cluster it found running

    def test_bench_fleet_section_tiny(self, ray):
        """The bench's fleet figures: ratios of the same run's 1-worker, 2-worker, Ray runs."""
        from reduced_dynamics import bench
        settings = bench.Settings(repeats=1, fleet_bags=2, fleet_bag_seconds=0.3, quick=True)
        report = bench.run_bench(settings, ['fleet'])
        figures = {f.name: f for f in report.figures}
        assert {f.section for f in report.figures} == {'fleet'}
        two = figures['replay-many, local pool, 2 workers']
        assert two.unit == 'bags/s' and two.ratio == two.median / two.baseline_median
        assert two.target == 'ratio >= 1.7'
        ray_figure = figures['replay-many, Ray on this machine, 2 CPUs']
        assert ray_figure.baseline_median == two.median and ray_figure.ratio > 0
        assert '2 Ray CPUs, a running cluster' in ray_figure.note
        assert ray.is_initialized()  # the bench left the cluster it found running


def _dies_on_paper_constant(job):
    """Run a bag, but end the worker process on paper_constant (module level: picklable)."""
    if job.name == 'paper_constant':
        os._exit(9)  # no exception, no clean-up: the process is gone
    return run_bag(job)


def test_a_worker_that_dies_fails_its_bag_and_the_fleet_goes_on(tmp_path, monkeypatch):
    """A bag that kills its worker process (as an out-of-memory kill would) is a failed row."""
    from reduced_dynamics import fleet
    monkeypatch.setattr(fleet, 'run_bag', _dies_on_paper_constant)
    out = tmp_path / 'out'
    manifest = tmp_path / 'planar.yaml'  # the planar bag's own robot
    manifest.write_text(f"bags:\n  - path: {DATA / 'planar_pose_only'}\n"
                        f"    urdf: {config_path('robots/planar_testbed.urdf')}\n"
                        f"    base_joint: planar\n")
    jobs = plan_jobs([str(DATA / 'paper_constant'), str(DATA / 'paper_thruster')],
                     str(out), {}, str(manifest))
    # With 2 workers a bag beside the one that dies may go down with it: tried again.
    result = run_fleet(jobs, str(out), 2, 'local', progress=False)
    assert [row['status'] for row in result.rows] == ['failed', 'ok', 'ok'], \
        [row['error'] for row in result.rows]
    assert 'BrokenProcessPool' in result.rows[0]['error'] and result.failed == 1


@pytest.mark.parametrize('backend, module', [('ray', 'ray'), ('dask', 'distributed')])
def test_a_missing_backend_is_a_clear_error(tmp_path, monkeypatch, capsys, backend, module):
    import sys
    monkeypatch.setitem(sys.modules, module, None)  # import fails as if not installed
    assert main(['replay-many', str(DATA / 'paper_constant'), '-o', str(tmp_path / 'o'),
                 '--backend', backend, '--quiet']) == 2
    assert f'the {module} backend is not installed' in capsys.readouterr().err
