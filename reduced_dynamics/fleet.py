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
Fleet replay: ``reduced-dynamics replay-many BAG_OR_DIR... -o OUTDIR``.

Every bag is replayed by :func:`reduced_dynamics.replay.replay` with ``replay``'s
options (per bag from a YAML manifest) into ``OUTDIR/<name>/bag`` with its
``OUTDIR/<name>/summary.json``; ``OUTDIR/fleet.csv`` and ``fleet.parquet`` hold
one row per bag. A bag that fails is a row with its error; a bag whose summary
holds the same options' hash is not replayed again. The bags run on a backend:
a local process pool (default), Ray or Dask distributed; every backend runs
:func:`run_bag` where the worker is and reads the bag from its path there
(a shared path on a cluster: nothing is shipped but the path).
"""

from __future__ import annotations

import argparse
from concurrent.futures import as_completed, Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager
import dataclasses
from dataclasses import dataclass
import functools
import hashlib
import importlib
import json
import multiprocessing
import os
from pathlib import Path
import sys
import time
from typing import Any, Callable, Iterator, NamedTuple, Optional, Sequence

import yaml

from reduced_dynamics.peak_memory import peak_resident_kib

BACKENDS = ('local', 'ray', 'dask')
TABLE_CSV = 'fleet.csv'
TABLE_PARQUET = 'fleet.parquet'
SUMMARY = 'summary.json'
OUTPUT_BAG = 'bag'
#: Largest exit status: the number of failed bags, capped below the shell's 126+.
EXIT_CAP = 125
#: Replay options that are the fleet's to set, not a bag's (per-bag outputs).
_FLEET_OWNED = {'bag', 'output', 'summary_json', 'overwrite', 'quiet', 'plots', 'causal_output'}
#: Options beside ReplayOptions' fields that turn into the robot or the parameters.
_ROBOT_AND_PARAMS = {'urdf', 'base_joint', 'gravity', 'params', 'cyclic_joints',
                     'prediction_mode', 'no_smooth'}
#: Options only replay-many knows (per bag as well).
FLEET_OPTIONS = {'command_mapping', 'plots'}
#: Options naming files whose content enters the options' hash.
_FILE_OPTIONS = ('urdf', 'params', 'command_mapping')


@dataclass(frozen=True)
class BagJob:
    """One bag of the fleet: where it is, where its outputs go, how it is replayed."""

    bag: str
    name: str
    out_dir: str
    options: dict
    options_hash: str = ''


# --- inputs: bags, manifest, options -------------------------------------------------------

def is_bag(path: Path) -> bool:
    """Return whether ``path`` is a rosbag2 directory or a bare .mcap/.db3 file."""
    if path.is_dir():
        return (path / 'metadata.yaml').is_file()
    return path.is_file() and path.suffix in ('.mcap', '.db3')


def find_bags(path: str | os.PathLike) -> list[Path]:
    """Return the bags ``path`` names: itself, or the rosbag2 bags under a directory."""
    root = Path(path)
    if is_bag(root):
        return [root]
    if not root.is_dir():
        raise FileNotFoundError(f'{root}: no such bag or directory')
    found: list[Path] = []
    for directory, subdirs, files in os.walk(root):
        here = Path(directory)
        if (here / 'metadata.yaml').is_file():
            found.append(here)
            subdirs.clear()  # a bag's own files are not bags
            continue
        subdirs.sort()
        # A bare .mcap outside a rosbag2 directory is a bag of its own.
        found.extend(here / f for f in sorted(files) if f.endswith('.mcap'))
    return sorted(found)


def replay_option_names() -> dict[str, argparse.Action]:
    """Return replay's command-line options a bag can set, by name (the argparse dest)."""
    from reduced_dynamics.replay import register_command, ReplayOptions
    commands = argparse.ArgumentParser(add_help=False).add_subparsers()
    register_command(commands)
    replay_parser = commands.choices['replay']
    fields = {f.name for f in dataclasses.fields(ReplayOptions)}
    return {a.dest: a for a in replay_parser._actions
            if a.dest not in _FLEET_OWNED and a.dest != 'help'
            and (a.dest in fields or a.dest in _ROBOT_AND_PARAMS)}


def load_manifest(path: str) -> tuple[dict, list[tuple[Path, dict]]]:
    """
    Return a manifest's defaults and its (path, options) entries, paths made absolute.

    Format::

        defaults: {urdf: robots/freeflyer.urdf, base_pose_topic: /vrpn_mocap/robot/pose}
        bags:
          - path: campaign/run_03        # a bag or a directory of bags
            start: 10.0
            end: 40.0
            params: {pose_position_noise: 0.001}   # or a parameters YAML file
          - path: campaign/run_03        # a named entry: a job of its own
            name: run_03-first-half
            end: 25.0

    Relative file paths (bags, urdf, params, command_mapping) are relative to the
    manifest's directory.
    """
    base = Path(path).resolve().parent
    with open(path, encoding='utf-8') as stream:
        try:
            data = yaml.safe_load(stream) or {}
        except yaml.YAMLError as error:
            raise ValueError(f'manifest {path}: not valid YAML: {error}') from None
    if not isinstance(data, dict) or set(data) - {'defaults', 'bags'}:
        raise ValueError(f'manifest {path}: expected the keys defaults and bags')
    known = set(replay_option_names()) | FLEET_OPTIONS

    def options(entry: Any, what: str) -> dict:
        if not isinstance(entry, dict):
            raise ValueError(f'manifest {path}: {what} must be a mapping of options')
        unknown = sorted(set(entry) - known - {'path', 'name'})
        if unknown:
            raise ValueError(f'manifest {path}: {what}: unknown options {unknown}; '
                             f'known: {sorted(known)}')
        resolved = dict(entry)
        for key in _FILE_OPTIONS:
            value = resolved.get(key)
            if isinstance(value, str) and value and not os.path.isabs(value) \
                    and (base / value).exists():
                resolved[key] = str(base / value)
        return resolved

    defaults = options(data.get('defaults') or {}, 'defaults')
    entries = []
    for i, entry in enumerate(data.get('bags') or []):
        if isinstance(entry, str):
            entry = {'path': entry}
        entry = options(entry, f'bags[{i}]')
        if not entry.get('path'):
            raise ValueError(f'manifest {path}: bags[{i}] needs a path')
        entries.append((Path(base, entry.pop('path')).resolve(), entry))
    return defaults, entries


def _file_digest(value: Any) -> Optional[str]:
    if isinstance(value, str) and value and os.path.isfile(value):
        with open(value, 'rb') as stream:
            return hashlib.sha256(stream.read()).hexdigest()
    return None


def options_hash(bag: Path, options: dict) -> str:
    """
    Return the hash that decides whether a bag's earlier outputs still hold.

    It covers the options, the content of the files they name (URDF, parameters,
    command mapping), the bag's files (size and modification time) and the
    package version.
    """
    from reduced_dynamics import __version__
    files = sorted(bag.rglob('*')) if bag.is_dir() else [bag]
    identity = {'options': options,
                'files': {k: _file_digest(options.get(k)) for k in _FILE_OPTIONS},
                'bag': [(f.name, f.stat().st_size, f.stat().st_mtime_ns)
                        for f in files if f.is_file()],
                'version': __version__}
    text = json.dumps(identity, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def plan_jobs(paths: Sequence[str], out_dir: str, options: dict,
              manifest: Optional[str] = None) -> list[BagJob]:
    """
    Return the fleet's jobs: every bag of ``paths`` and of the manifest, once, in order.

    A bag's options: ``options`` (the command line), then the manifest's defaults,
    then every manifest entry whose path is the bag or a directory holding it. A
    manifest entry with a ``name`` is a job of its own (one bag, e.g. a time window
    of a bag that is also replayed whole) and applies to no other bag.
    """
    defaults, entries = load_manifest(manifest) if manifest else ({}, [])
    shared = [(path, entry) for path, entry in entries if 'name' not in entry]
    planned: list[tuple[Path, Optional[dict]]] = []
    seen: set = set()
    for path in [*paths, *(p for p, e in entries if 'name' not in e)]:
        for bag in find_bags(path):
            bag = bag.resolve()
            if bag not in seen:
                seen.add(bag)
                planned.append((bag, None))
    for path, entry in entries:
        if 'name' in entry:
            if not is_bag(path):
                raise ValueError(f'manifest {manifest}: {entry["name"]}: {path} is not a bag '
                                 '(an entry with a name is one bag)')
            planned.append((path, entry))
    if not planned:
        raise FileNotFoundError('no bag found in ' + ', '.join(map(str, paths or [manifest])))
    jobs, names = [], set()
    for bag, own in planned:
        merged = {k: v for k, v in options.items() if v is not None}
        merged.update(defaults)
        if own is None:
            for path, entry in shared:
                if bag == path or path in bag.parents:
                    merged.update(entry)
            name = bag.stem if bag.is_file() else bag.name
        else:
            merged.update({k: v for k, v in own.items() if k != 'name'})
            name = str(own['name'])
            if not name or name.startswith('.') \
                    or not all(c.isalnum() or c in '-_.' for c in name):
                raise ValueError(f'manifest {manifest}: name {name!r}: use letters, digits, '
                                 '"-", "_" and "."')
        unique, k = name, 2
        while unique in names:
            unique, k = f'{name}-{k}', k + 1
        names.add(unique)
        jobs.append(BagJob(str(bag), unique, str(Path(out_dir, unique).resolve()),
                           merged, options_hash(bag, merged)))
    return jobs


# --- one bag, on a worker -----------------------------------------------------------------

@functools.lru_cache(maxsize=8)
def _robot(urdf: str, base_joint: Optional[str], gravity: Optional[tuple],
           params_robot: str) -> Any:
    """Return the robot model (cached per worker: a fleet is mostly one robot)."""
    from reduced_dynamics.replay import load_robot_from_params
    params = json.loads(params_robot)
    return load_robot_from_params(params, urdf, base_joint,
                                  None if gravity is None else list(gravity))


def replay_inputs(options: dict, out_dir: str) -> tuple[Any, Any]:
    """Return the robot and the ReplayOptions of a bag's options (as ``replay`` builds them)."""
    from reduced_dynamics.params import defaults, load_params_file
    from reduced_dynamics.replay import ReplayOptions
    source = options.get('params')
    if isinstance(source, dict):
        params = {**defaults(), **source}
    else:
        params = load_params_file(source) if source else defaults()
    for key in ('cyclic_joints', 'prediction_mode'):
        if options.get(key) is not None:
            params[key] = options[key]
    gravity = options.get('gravity')
    robot = _robot(options.get('urdf') or '', options.get('base_joint'),
                   None if gravity is None else tuple(gravity),
                   json.dumps({k: params.get(k) for k in ('robot_description', 'urdf_path',
                                                          'base_joint', 'gravity')}))
    fields = {f.name for f in dataclasses.fields(ReplayOptions)}
    given = {k: v for k, v in options.items()
             if k in fields and k not in ('params', 'progress', 'overwrite', 'plots_dir')}
    if options.get('command_mapping') and not given.get('thruster_map'):
        given['thruster_map'] = options['command_mapping']  # the plots draw that command
    replay_options = ReplayOptions(
        params=params, overwrite=True, smooth=not options.get('no_smooth', False),
        plots_dir=os.path.join(out_dir, 'plots') if options.get('plots') else None, **given)
    return robot, replay_options


def _correlation(bag: str, out_bag: str, summary: dict, mapping_path: str) -> dict:
    """Return the command correlation columns (or the reason there are none)."""
    from reduced_dynamics.command_mapping import CommandMapping
    from reduced_dynamics.thrust_correlation import thrust_correlation
    try:
        mapping = CommandMapping.load(mapping_path)
        figures = thrust_correlation(bag, out_bag, pose_topic=summary['base_topic'],
                                     mapping=mapping)
    except (ValueError, KeyError, OSError) as error:
        return {'error': str(error)}
    return {'fx': figures.fx, 'fy': figures.fy, 'mz': figures.mz, 'samples': figures.samples}


def _write_json(path: str, data: dict) -> None:
    """Write ``data`` whole or not at all (a resumed fleet trusts what it finds)."""
    partial = path + '.partial'
    with open(partial, 'w', encoding='utf-8') as stream:
        json.dump(data, stream, indent=2, default=str)
    os.replace(partial, path)


def run_bag(job: BagJob) -> dict:
    """Replay one bag where this worker runs; return its table row (never raises)."""
    from reduced_dynamics.bag.reader import open_bag
    from reduced_dynamics.blas_threads import limit_blas_threads
    from reduced_dynamics.replay import replay
    started = time.perf_counter()
    summary_path = os.path.join(job.out_dir, SUMMARY)
    out_bag = os.path.join(job.out_dir, OUTPUT_BAG)
    try:
        # Whichever backend's process this is (a pool worker, Ray, Dask): one BLAS thread
        # for it, also for the correlation after the replay (reduced_dynamics.blas_threads).
        limit_blas_threads()
        os.makedirs(job.out_dir, exist_ok=True)
        if os.path.exists(summary_path):
            os.remove(summary_path)  # outputs of other options: not this job's
        robot, options = replay_inputs(job.options, job.out_dir)
        with open_bag(job.bag) as reader:
            duration = reader.duration
        summary = replay(job.bag, out_bag, robot, options)
        fleet = {'options_hash': job.options_hash, 'options': job.options,
                 'bag_duration_s': duration}
        if job.options.get('command_mapping'):
            fleet['command_correlation'] = _correlation(job.bag, out_bag, summary,
                                                        job.options['command_mapping'])
        fleet['wall_s'] = time.perf_counter() - started
        # The worker's high-water mark so far (Linux: KiB): the fleet's largest is
        # the memory one worker needs.
        fleet['worker_peak_rss_mib'] = peak_resident_kib() / 1024
        summary['fleet'] = fleet
        _write_json(summary_path, summary)
        return fleet_row(job, summary)
    # The fleet goes on whatever one bag does: anything it raises is that bag's row.
    except Exception as error:  # noqa: B902
        return {**_job_columns(job), 'status': 'failed',
                'error': f'{type(error).__name__}: {error}',
                'wall_s': time.perf_counter() - started}


# --- the table ----------------------------------------------------------------------------

def _job_columns(job: BagJob) -> dict:
    return {'name': job.name, 'bag': job.bag, 'status': None, 'error': None,
            'resumed': False, 'options_hash': job.options_hash}


def _column(text: str) -> str:
    """Return ``text`` as a column-name piece (letters, digits, underscores)."""
    return ''.join(c if c.isalnum() else '_' for c in text).strip('_').lower()


def fleet_row(job: BagJob, summary: dict) -> dict:
    """Return a bag's table row from its summary (see docs/fleet.md for the columns)."""
    fleet = summary.get('fleet', {})
    damage = summary.get('damage') or {}
    rejected = summary.get('rejected') or {}
    row = {**_job_columns(job),
           'status': 'damaged' if damage.get('damaged') else 'ok',
           'robot': summary.get('robot'),
           'base_topic': summary.get('base_topic'),
           'joint_states_topic': summary.get('joint_states_topic'),
           'duration_s': fleet.get('bag_duration_s'),
           'window_start_s': job.options.get('start'),
           'window_end_s': job.options.get('end'),
           'inputs_received': sum((summary.get('messages_in') or {}).values()),
           'processed': summary.get('processed'),
           'rejected': sum(rejected.values())}
    for reason, count in sorted(rejected.items()):
        row[f'rejected_{_column(reason)}'] = count
    row.update({'damaged': bool(damage.get('damaged')),
                'damage_regions': len(damage.get('regions') or []),
                'messages_lost': damage.get('messages_lost'),
                'bytes_lost': damage.get('bytes_lost'),
                'undecodable': damage.get('undecodable'),
                'events': len(summary.get('events') or [])})
    spread = summary.get('mu_spread') or []
    row['mu_spread_max'] = max(spread) if spread else None
    for i, value in enumerate(spread):
        row[f'mu_spread_{i}'] = value
    for key, value in (summary.get('filter') or {}).items():
        if isinstance(value, (int, float)):
            row[f'filter_{key}'] = value
    row.update({'predictions': summary.get('predictions'),
                'prediction_shape_residual_median':
                    summary.get('prediction_shape_residual_median'),
                'replay_s': summary.get('seconds'),
                'wall_s': fleet.get('wall_s'),
                'worker_peak_rss_mib': fleet.get('worker_peak_rss_mib')})
    correlation = fleet.get('command_correlation')
    if correlation is not None:
        row.update({'corr_fx': correlation.get('fx'), 'corr_fy': correlation.get('fy'),
                    'corr_mz': correlation.get('mz'),
                    'corr_samples': correlation.get('samples'),
                    'corr_error': correlation.get('error')})
    row['output_bag'] = os.path.join(job.name, OUTPUT_BAG)
    row['summary'] = os.path.join(job.name, SUMMARY)
    return row


def resumed_row(job: BagJob) -> Optional[dict]:
    """Return the row of a bag already replayed with the same options' hash, else None."""
    path = os.path.join(job.out_dir, SUMMARY)
    try:
        with open(path, encoding='utf-8') as stream:
            summary = json.load(stream)
    except (OSError, ValueError):
        return None
    if summary.get('fleet', {}).get('options_hash') != job.options_hash \
            or not os.path.isdir(os.path.join(job.out_dir, OUTPUT_BAG)):
        return None
    return {**fleet_row(job, summary), 'resumed': True}


def write_table(rows: list[dict], out_dir: str) -> tuple[str, str]:
    """Write ``fleet.csv`` and ``fleet.parquet`` (pyarrow), one row per bag; return the paths."""
    import pyarrow as pa
    import pyarrow.csv
    import pyarrow.parquet
    columns: list[str] = []
    for row in rows:
        columns.extend(k for k in row if k not in columns)
    table = pa.Table.from_pylist([{c: row.get(c) for c in columns} for row in rows])
    csv_path = os.path.join(out_dir, TABLE_CSV)
    parquet_path = os.path.join(out_dir, TABLE_PARQUET)
    pyarrow.csv.write_csv(table, csv_path)
    pyarrow.parquet.write_table(table, parquet_path)
    return csv_path, parquet_path


def read_table(path: str) -> list[dict]:
    """Return a fleet table (.parquet or .csv) as rows."""
    import pyarrow.csv
    import pyarrow.parquet
    table = pyarrow.parquet.read_table(path) if str(path).endswith('.parquet') \
        else pyarrow.csv.read_csv(path)
    return table.to_pylist()


def plot_fleet(table: str | list[dict], png: str,
               columns: Sequence[str] = ('corr_fx', 'corr_fy', 'corr_mz'),
               title: str = 'correlation of the wrench estimate with the command') -> str:
    """Plot one figure per bag across the fleet (grouped bars: one per column); return png."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    import numpy as np
    rows = read_table(table) if isinstance(table, (str, os.PathLike)) else table
    rows = [r for r in rows if r.get('status') in ('ok', 'damaged')]
    if not rows:
        raise ValueError('no replayed bag in the table to plot')
    width = 0.8 / len(columns)
    x = np.arange(len(rows))
    fig, ax = plt.subplots(figsize=(max(6.0, 0.9 * len(rows) + 2.0), 3.6))
    for i, column in enumerate(columns):
        values = [np.nan if r.get(column) is None else r[column] for r in rows]
        ax.bar(x + (i - (len(columns) - 1) / 2) * width, values, width,
               label=column.replace('corr_', ''))
    ax.set_xticks(x, [r['name'] for r in rows], rotation=30, ha='right', fontsize=8)
    ax.set_title(title, fontsize=10)
    ax.axhline(0.0, color='black', linewidth=0.5)
    ax.grid(True, axis='y', alpha=0.3)
    ax.legend(fontsize=8, loc='upper left', bbox_to_anchor=(1.0, 1.0))
    fig.tight_layout()
    fig.savefig(png, dpi=80)
    plt.close(fig)
    return png


# --- backends -----------------------------------------------------------------------------

Submit = Callable[[BagJob], Future]


class Slots(NamedTuple):
    """What a backend offers: submit(job) -> Future, and how many bags run at once."""

    submit: Submit
    count: int


def _import_backend(module: str) -> Any:
    """Return the backend's module, or a ValueError saying how to install it."""
    try:
        return importlib.import_module(module)
    except ImportError as error:
        raise ValueError(f'the {module} backend is not installed ({error}): pip install '
                         '"reduced_dynamics[fleet]" (Ray and Dask distributed)') from None


@contextmanager
def local_backend(workers: Optional[int]) -> Iterator[Slots]:
    """
    Yield a local process pool of ``workers`` (default: the CPU count), one bag each.

    A worker that dies (killed, out of memory, a crash in native code) breaks the
    pool: the bags it held fail with that error and the next bag gets a new pool
    (:func:`run_fleet` tries each such bag twice).
    """
    count = workers or os.cpu_count() or 1
    # forkserver: workers forked from a clean server that imported replay once (~1 s
    # each under spawn), not from the driver, whose threads (tqdm, a Ray or Dask client
    # of an earlier run, gRPC) a plain fork would copy in an unknown state.
    if 'forkserver' in multiprocessing.get_all_start_methods():
        context = multiprocessing.get_context('forkserver')
        context.set_forkserver_preload(['reduced_dynamics.fleet', 'reduced_dynamics.replay'])
    else:
        context = multiprocessing.get_context('spawn')
    pools = [ProcessPoolExecutor(max_workers=count, mp_context=context)]

    def submit(job: BagJob) -> Future:
        try:
            return pools[-1].submit(run_bag, job)
        except BrokenProcessPool:
            pools[-1].shutdown(wait=False)
            pools.append(ProcessPoolExecutor(max_workers=count, mp_context=context))
            return pools[-1].submit(run_bag, job)
    try:
        yield Slots(submit, count)
    finally:
        for pool in pools:
            pool.shutdown()


@contextmanager
def ray_backend(workers: Optional[int], address: Optional[str]) -> Iterator[Slots]:
    """
    Yield Ray: an existing cluster at ``address``, else a local one of ``workers`` CPUs.

    A task takes one CPU; the bag is read by the node the task lands on, from the
    same path: on a cluster, the bags and OUTDIR must be on a shared filesystem.
    ``workers`` bags run at once (default: the cluster's CPUs).
    """
    ray = _import_backend('ray')
    started = not ray.is_initialized()
    if started:
        kwargs: dict[str, Any] = {'address': address} if address \
            else {'num_cpus': workers or os.cpu_count() or 1}
        try:
            ray.init(include_dashboard=False, log_to_driver=False, **kwargs)
        except Exception as error:  # noqa: B902 (Ray raises many kinds; all mean "no cluster")
            raise ValueError(f'cannot start or reach Ray ({address or "local"}): '
                             f'{error}') from error
    remote = ray.remote(num_cpus=1, max_retries=0)(run_bag)
    try:
        count = workers or max(int(ray.cluster_resources().get('CPU', 1)), 1)
        yield Slots(lambda job: remote.remote(job).future(), count)
    finally:
        if started:
            ray.shutdown()


@contextmanager
def dask_backend(workers: Optional[int], address: Optional[str]) -> Iterator[Slots]:
    """
    Yield Dask distributed: the scheduler at ``address``, else a local cluster.

    The local cluster has ``workers`` single-threaded processes (default: the CPU
    count); ``workers`` bags run at once (default: the cluster's threads).
    """
    distributed = _import_backend('distributed')
    Client, LocalCluster = distributed.Client, distributed.LocalCluster
    if address:
        try:
            client = Client(address, timeout=30)
        except OSError as error:  # TimeoutError, connection refused
            raise ValueError(f'cannot reach the Dask scheduler at {address}: '
                             f'{error}') from error
    else:
        client = Client(LocalCluster(n_workers=workers or os.cpu_count() or 1,
                                     threads_per_worker=1, processes=True,
                                     dashboard_address=None))
    try:
        executor = client.get_executor(pure=False)
        count = workers or max(sum(client.nthreads().values()), 1)
        yield Slots(functools.partial(executor.submit, run_bag), count)
    finally:
        cluster = client.cluster
        client.close()
        if not address and cluster is not None:
            cluster.close()


def backend(name: str, workers: Optional[int] = None, address: Optional[str] = None) -> Any:
    """Return the context manager of backend ``name`` (it yields :class:`Slots`)."""
    if workers is not None and workers < 1:
        raise ValueError(f'workers must be >= 1, got {workers}')
    if name == 'local':
        if address:
            raise ValueError('--address is for the ray and dask backends')
        return local_backend(workers)
    if name == 'ray':
        return ray_backend(workers, address)
    if name == 'dask':
        return dask_backend(workers, address)
    raise ValueError(f'unknown backend {name!r}; choose from {", ".join(BACKENDS)}')


# --- the fleet ----------------------------------------------------------------------------

@dataclass
class FleetResult:
    """Rows in the jobs' order, and where the table went."""

    rows: list[dict]
    csv: str
    parquet: str

    @property
    def failed(self) -> int:
        """Return the number of bags that failed."""
        return sum(r['status'] == 'failed' for r in self.rows)


def run_fleet(jobs: Sequence[BagJob], out_dir: str, workers: Optional[int] = None,
              backend_name: str = 'local', address: Optional[str] = None,
              progress: bool = True) -> FleetResult:
    """Replay ``jobs`` (resuming where the options' hash matches); write the table."""
    from tqdm import tqdm
    os.makedirs(out_dir, exist_ok=True)
    rows: dict[int, dict] = {}
    todo = []
    for index, job in enumerate(jobs):
        row = resumed_row(job)
        if row is None:
            todo.append(index)
        else:
            rows[index] = row
    counts = {'ok': 0, 'damaged': 0, 'failed': 0}
    bar = tqdm(total=len(jobs), initial=len(rows), unit='bag', disable=not progress,
               file=sys.stderr, dynamic_ncols=True)
    bar.set_postfix_str(f'{len(rows)} resumed')

    def finished(index: int, row: dict) -> None:
        rows[index] = row
        counts[row['status']] = counts.get(row['status'], 0) + 1
        bar.set_postfix_str(f'{row["name"]}: {row["status"]}; ' + ', '.join(
            f'{k} {v}' for k, v in counts.items()), refresh=False)
        bar.update(1)

    try:
        if todo:
            with backend(backend_name, workers, address) as (submit, slots):
                # At most `slots` bags in flight: the backends' queues stay short and
                # the progress bar tells what runs now.
                pending: dict[Future, int] = {}
                queue, retries = list(todo), []
                attempts = dict.fromkeys(todo, 0)
                while queue or retries or pending:
                    if retries and not pending:
                        # Alone: a bag that ends its worker again takes no other with it.
                        index = retries.pop(0)
                        attempts[index] += 1
                        pending[submit(jobs[index])] = index
                    while queue and not retries and len(pending) < slots:
                        index = queue.pop(0)
                        attempts[index] += 1
                        pending[submit(jobs[index])] = index
                    done = next(as_completed(pending))
                    index = pending.pop(done)
                    try:
                        row = done.result()
                    # run_bag never raises: this is the worker itself (killed, out of
                    # memory, a crash). It takes the bags beside it down too, so each
                    # gets a second try, alone; a bag that ends its worker twice fails.
                    except Exception as error:  # noqa: B902
                        if attempts[index] < 2:
                            retries.append(index)
                            continue
                        row = {**_job_columns(jobs[index]), 'status': 'failed',
                               'error': f'worker: {type(error).__name__}: {error}'}
                    finished(index, row)
    finally:
        bar.close()
    ordered = [rows[i] for i in range(len(jobs)) if i in rows]
    csv_path, parquet_path = write_table(ordered, out_dir)
    return FleetResult(ordered, csv_path, parquet_path)


def _run(args: argparse.Namespace) -> int:
    names = replay_option_names()
    options = {name: getattr(args, name) for name in names if hasattr(args, name)}
    options['command_mapping'] = os.path.abspath(args.command_mapping) \
        if args.command_mapping else None
    options['plots'] = args.plots or None
    for key in ('urdf', 'params'):
        if options.get(key):
            options[key] = os.path.abspath(options[key])
    if not args.bags and not args.manifest:
        raise ValueError('give bags or directories of bags, or a --manifest')
    if args.workers is not None and args.workers < 1:
        raise ValueError(f'--workers must be >= 1, got {args.workers}')
    jobs = plan_jobs(args.bags, args.output, options, args.manifest)
    result = run_fleet(jobs, args.output, args.workers, args.backend, args.address,
                       progress=not args.quiet)
    counts: dict[str, int] = {}
    for row in result.rows:
        counts[row['status']] = counts.get(row['status'], 0) + 1
    resumed = sum(bool(r.get('resumed')) for r in result.rows)
    print(f'{len(result.rows)} bags: ' + ', '.join(f'{k} {v}' for k, v in sorted(counts.items()))
          + f' ({resumed} resumed); table {result.csv}, {result.parquet}')
    for row in result.rows:
        if row['status'] == 'failed':
            print(f'  FAILED {row["bag"]}: {row["error"]}', file=sys.stderr)
    return min(result.failed, EXIT_CAP)


def register_command(commands: Any) -> None:
    """Add the ``replay-many`` subcommand (replay's options apply to every bag)."""
    parser = commands.add_parser(
        'replay-many', help='replay many bags (a test campaign) into one table',
        description='Replay every bag with replay\'s options (per bag from --manifest); '
                    'write OUTDIR/<bag>/bag, OUTDIR/<bag>/summary.json, OUTDIR/fleet.csv and '
                    'OUTDIR/fleet.parquet. Exit status: the number of failed bags.')
    parser.add_argument('bags', nargs='*', metavar='BAG_OR_DIR',
                        help='rosbag2 bags, .mcap files, or directories searched for bags')
    parser.add_argument('-o', '--output', required=True, metavar='OUTDIR')
    parser.add_argument('--workers', type=int, default=None,
                        help='bags replayed at once (default: the CPU count; on a Ray or '
                             'Dask cluster, its CPUs)')
    parser.add_argument('--backend', choices=BACKENDS, default='local',
                        help='local process pool (default), Ray or Dask distributed')
    parser.add_argument('--address', help='Ray cluster or Dask scheduler address (default: '
                                          'start one on this machine)')
    parser.add_argument('--manifest', metavar='FILE',
                        help='YAML of per-bag options (defaults, bags: [{path, ...}])')
    parser.add_argument('--command-mapping', metavar='FILE',
                        help='YAML mapping a thruster command message to a body wrench '
                             '(e.g. config/thrusters/freeflyer2.yaml): adds the '
                             'correlation columns')
    parser.add_argument('--plots', action='store_true', help='write each bag\'s plots')
    parser.add_argument('--quiet', action='store_true', help='no progress bar')
    for action in replay_option_names().values():
        parser._add_action(action)  # replay's own options, the same objects
    parser.set_defaults(func=_run)
