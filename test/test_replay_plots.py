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

"""
``replay --plots`` fitted to the robot (issue 24 item 6), checked on the figure objects.

Matplotlib's Agg backend; the figures ``replay_plots.make_figures`` returns are kept
(closing a figure leaves it inspectable) and read: axes, line labels and data, legend
and axes bounding boxes. No pixel comparison.
"""

from pathlib import Path

from matplotlib.backends.backend_agg import FigureCanvasAgg
import numpy as np
import pytest

from reduced_dynamics import replay_plots
from reduced_dynamics.bag.reader import open_bag
from reduced_dynamics.params import defaults
from reduced_dynamics.replay import replay, ReplayOptions
from reduced_dynamics.resources import config_path
from reduced_dynamics.robot.model import load_robot
from reduced_dynamics.thrust_correlation import commanded_world

DATA = Path(__file__).parent / 'data'
PD_BAG = str(DATA / 'freeflyer2' / 'rosbag2_2024_03_14-14_17_23')
MOCAP = '/vrpn_mocap/robot/pose'
#: The axes' marks (thruster pulses, torque steps) also have legend entries.
MARK_LABELS = ('thruster on', 'joint torque change')


def _replayed_figures(monkeypatch, tmp_path, bag, robot, **options):
    kept, drawn = {}, {}
    make = replay_plots.make_figures

    def keep(series, *args, **kwargs):
        figures = make(series, *args, **kwargs)
        kept.update(figures)
        drawn['series'] = series
        return figures
    monkeypatch.setattr(replay_plots, 'make_figures', keep)
    summary = replay(bag, str(tmp_path / 'out'), robot,
                     ReplayOptions(params=defaults(), plots_dir=str(tmp_path / 'plots'),
                                   **options))
    assert sorted(Path(p).name for p in summary['plots']) == sorted(kept)
    return kept, dict(summary, series=drawn['series'])


def _labels(ax):
    return [line.get_label() for line in ax.get_lines()
            if not line.get_label().startswith('_')
            and not line.get_label().startswith(MARK_LABELS)]


def _line(ax, label):
    [line] = [line for line in ax.get_lines() if line.get_label() == label]
    return line


@pytest.fixture(scope='module')
def freeflyer2(tmp_path_factory):
    """Return the figures and summary of the shipped planar recording (thruster commands)."""
    monkeypatch = pytest.MonkeyPatch()
    try:
        figures, summary = _replayed_figures(
            monkeypatch, tmp_path_factory.mktemp('ff2'), PD_BAG,
            load_robot(str(config_path('robots/freeflyer.urdf'))), base_pose_topic=MOCAP)
    finally:
        monkeypatch.undo()
    return figures, summary


def test_planar_plots_draw_fx_fy_tz_about_the_centre_of_mass(freeflyer2):
    figures, _ = freeflyer2
    drift = figures['drift.png']
    force, torque = drift.axes
    assert _labels(force) == ['F_x', 'F_x commanded', 'F_y', 'F_y commanded']
    assert _labels(torque) == ['T_z', 'T_z commanded']
    assert torque.get_ylabel() == 'torque about centre of mass [N m]'
    momentum = figures['momentum.png']
    assert [_labels(ax) for ax in momentum.axes] == [['p_x', 'p_y'], ['L_z']]
    assert 'about centre of mass' in momentum.axes[1].get_ylabel()


def test_the_commanded_wrench_is_the_correlation_functions(freeflyer2):
    """The drawn command is thrust_correlation's (the data README's thruster map)."""
    figures, summary = freeflyer2
    force, torque = figures['drift.png'].axes
    stamps = [row[0] for row in summary['series']['rate'].rows]  # the drawn estimates'
    expected, _ = commanded_world(PD_BAG, stamps, MOCAP)
    drawn = np.column_stack([_line(force, 'F_x commanded').get_ydata(),
                             _line(force, 'F_y commanded').get_ydata(),
                             _line(torque, 'T_z commanded').get_ydata()])
    assert len(drawn) == len(expected)  # 6569 estimates: below the series' decimation
    # The body origin is the centre of mass (freeflyer.urdf): no lever arm. The yaw of
    # the normalised quaternion (here) and of the raw one (there) differ: 1.0e-7 N at most.
    np.testing.assert_allclose(drawn, expected, rtol=0.0, atol=1e-6)
    assert 'commanded (nominal): /robot/commands/binary_thrust' in force.get_title()


def _figure_checks(figures):
    for name, fig in figures.items():
        canvas = FigureCanvasAgg(fig)  # pyplot's close left the figure without one
        canvas.draw()  # as savefig laid it out (constrained layout)
        renderer = canvas.get_renderer()
        page = fig.bbox
        for ax in fig.axes:
            if ax.get_yscale() == 'log':
                for line in ax.get_lines():
                    y = np.asarray(line.get_ydata(), dtype=float)
                    assert np.all(y[np.isfinite(y)] > 0.0), (name, line.get_label())
            legend = ax.get_legend()
            if legend is None:
                continue
            box = legend.get_window_extent(renderer)
            # Outside every axes (it covers no data) and inside the page (not cut off).
            for other in fig.axes:
                assert not box.overlaps(other.get_window_extent(renderer)), name
            assert page.x0 <= box.x0 and box.x1 <= page.x1 + 0.5, name
            assert page.y0 <= box.y0 and box.y1 <= page.y1 + 0.5, name


def test_no_zero_on_log_axes_and_no_legend_over_data(freeflyer2):
    figures, _ = freeflyer2
    _figure_checks(figures)
    residual = figures['prediction_residual.png'].axes[0]
    assert residual.get_yscale() == 'log'
    # The free-flyer has no joints: its shape residual is 0 throughout, and said so.
    assert _labels(residual) == ['base position [m]']
    assert 'shape residual 0 throughout (not drawn)' in residual.get_title()


def test_spatial_robot_plots_six_components(monkeypatch, tmp_path):
    figures, _ = _replayed_figures(monkeypatch, tmp_path, str(DATA / 'paper_thruster'),
                                   load_robot())
    force, torque = figures['drift.png'].axes
    assert _labels(force) == ['F_x', 'F_y', 'F_z']
    assert _labels(torque) == ['T_x', 'T_y', 'T_z']
    assert torque.get_ylabel() == 'torque about centre of mass [N m]'
    _figure_checks(figures)


def test_some_zero_residuals_are_left_out_and_counted():
    series = {'mu': _Rows([]), 'rate': _Rows([]), 'shape': _Rows([]),
              'residual': _Rows([(0, 0.0, 1e-3), (10**9, 2e-4, 0.0), (2 * 10**9, 3e-4, 2e-3)])}
    figures = replay_plots.make_figures(series, load_robot())
    ax = figures['prediction_residual.png'].axes[0]
    assert _labels(ax) == ['shape [rad] (1 of 3 zero, not drawn)',
                           'base position [m] (1 of 3 zero, not drawn)']
    _figure_checks(figures)


class _Rows:
    def __init__(self, rows):
        self.rows = rows


@pytest.mark.parametrize('name', ['paper_constant', 'paper_thruster'])
def test_centre_of_mass_moves_with_the_linear_momentum(name):
    """c_dot = p / M while the arm moves (constant: p = 0; thruster: p changes)."""
    import pinocchio as pin
    robot = load_robot()
    bag = str(DATA / name)
    rows, truth = [], []
    with open_bag(bag) as reader:
        for message in reader.messages(['/joint_states', '/ground_truth/momentum']):
            msg = message.msg
            stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
            if message.topic == '/joint_states':
                position = dict(zip(msg.name, msg.position))
                rows.append((stamp, *(position[n] for n in robot.shape_joint_names)))
            else:
                truth.append((stamp, msg.wrench.force.x, msg.wrench.force.y,
                              msg.wrench.force.z))
    shape = replay_plots.Table.of(rows)
    poses = replay_plots.read_poses(bag, '/odom')
    com, _, _ = replay_plots.centre_of_mass(robot, shape.stamps, poses, shape)
    momentum = replay_plots.Table.of(truth)
    p = momentum.values[np.searchsorted(momentum.stamps, shape.stamps)]
    t = shape.stamps * 1e-9
    # c(t) - c(0) against the integral of p / M (trapezoids over the 100 Hz record).
    moved = com - com[0]
    integral = np.vstack([np.zeros(3), np.cumsum(
        0.5 * (p[1:] + p[:-1]) * np.diff(t)[:, None], axis=0)]) \
        / pin.computeTotalMass(robot.model)
    scale = max(np.abs(integral).max(), 1e-3)  # paper_constant: p = 0, c stays
    # Measured: 5e-12 m (constant), 5.8e-9 m of 0.054 m (thruster).
    assert np.abs(moved - integral).max() <= 1e-5 * scale


def test_a_bad_thruster_map_is_named_on_the_plot_not_a_crash(monkeypatch, tmp_path):
    bad = tmp_path / 'bad.yaml'
    bad.write_text('command: {topic: /robot/commands/binary_thrust}\n')
    figures, summary = _replayed_figures(
        monkeypatch, tmp_path, PD_BAG, load_robot(str(config_path('robots/freeflyer.urdf'))),
        base_pose_topic=MOCAP, end=5.0, thruster_map=str(bad))
    force, torque = figures['drift.png'].axes
    assert _labels(force) == ['F_x', 'F_y'] and _labels(torque) == ['T_z']
    assert f'commanded wrench not drawn: {bad}: command needs type, field' in force.get_title()


def test_replay_many_plots_draw_the_command_of_its_command_mapping(tmp_path):
    from reduced_dynamics.fleet import replay_inputs
    mapping = str(config_path('thrusters/freeflyer2.yaml'))
    _, options = replay_inputs({'command_mapping': mapping, 'plots': True}, str(tmp_path))
    assert options.thruster_map == mapping
    _, own = replay_inputs({'command_mapping': mapping, 'thruster_map': 'other.yaml'},
                           str(tmp_path))
    assert own.thruster_map == 'other.yaml'
