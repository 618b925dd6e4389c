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
Issue 24.3: scripts/test.sh changes only the checkout; apt only when asked, never upgrading.

scripts/system_packages.sh runs against stand-ins for dpkg-query, apt-cache,
apt-get and sudo that log every call, so what it would do to the system is seen
without doing it.
"""

import os
from pathlib import Path
import re
import shutil
import stat
import subprocess
import sys

import pytest

try:
    from linters import find_linter, linter_env, search_path
except ImportError:  # test/ imported as a package
    from test.linters import find_linter, linter_env, search_path

REPO = Path(__file__).resolve().parent.parent
SCRIPT = REPO / 'scripts' / 'system_packages.sh'
LINTER_SCRIPT = REPO / 'scripts' / 'linter_packages.sh'
#: An apt-get -s line for an installed library apt would upgrade (what libxml2-utils did).
UPGRADE = 'Inst libxml2 [2.9.14+dfsg-1.3~deb12u1] (2.9.14+dfsg-1.3~deb12u6 Debian:12 [amd64])'
NEW = 'Inst libxml2-utils (2.9.14+dfsg-1.3~deb12u6 Debian:12 [amd64])'

SHIMS = {
    'dpkg-query': 'for p in $FAKE_INSTALLED; do [ "$p" = "${@: -1}" ] && '
                  '{ echo "install ok installed"; exit 0; }; done; exit 1',
    'apt-cache': 'echo "apt-cache $*" >> "$FAKE_LOG"; for p in $FAKE_KNOWN; do '
                 '[ "$p" = "${@: -1}" ] && exit 0; done; exit 100',
    'apt-get': 'echo "apt-get $*" >> "$FAKE_LOG"; '
               '[ "$1" = -s ] && printf "%b" "$FAKE_SIMULATION"; exit 0',
    'sudo': '[ "$1" = -n ] && shift; "$@"',
}


def run(tmp_path, *packages, installed=(), known=None, simulation='', rd_apt=None):
    """Run system_packages.sh PACKAGES with the stand-ins; return (code, output, apt calls)."""
    shims = tmp_path / 'bin'
    shims.mkdir(exist_ok=True)
    for name, body in SHIMS.items():
        path = shims / name
        path.write_text('#!/usr/bin/env bash\n' + body + '\n')
        path.chmod(path.stat().st_mode | stat.S_IEXEC)
    log = tmp_path / 'calls.log'
    log.write_text('')
    env = dict(os.environ, PATH=f'{shims}{os.pathsep}{os.environ["PATH"]}',
               FAKE_INSTALLED=' '.join(installed), FAKE_LOG=str(log),
               FAKE_KNOWN=' '.join(packages if known is None else known),
               FAKE_SIMULATION=simulation)
    env.pop('RD_APT', None)
    if rd_apt is not None:
        env['RD_APT'] = rd_apt
    done = subprocess.run(['bash', str(SCRIPT), *packages], env=env, capture_output=True,
                          text=True, timeout=120)
    return done.returncode, done.stdout + done.stderr, log.read_text().splitlines()


PACKAGES = ('python3-ament-copyright', 'python3-ament-xmllint', 'libxml2-utils')


def test_without_rd_apt_nothing_is_installed_and_the_missing_are_named(tmp_path):
    code, output, calls = run(tmp_path, *PACKAGES, installed=PACKAGES[:1])
    assert code == 1 and calls == []
    assert 'missing (not installed: RD_APT=1 installs them): python3-ament-xmllint ' \
           'libxml2-utils' in output


def test_nothing_missing_calls_no_apt(tmp_path):
    code, output, calls = run(tmp_path, *PACKAGES, installed=PACKAGES, rd_apt='1')
    assert (code, calls) == (0, [])


def test_rd_apt_installs_only_the_missing_without_upgrading(tmp_path):
    code, output, calls = run(tmp_path, *PACKAGES, installed=PACKAGES[:2], rd_apt='1',
                              simulation=NEW + '\n')
    assert code == 0, output
    installs = [c for c in calls if c.startswith('apt-get install')]
    assert installs == ['apt-get install -y -q --no-install-recommends --no-upgrade '
                        'libxml2-utils']
    assert not any(c.startswith('apt-get update') for c in calls)  # the lists knew it


def test_rd_apt_refuses_what_would_upgrade_an_installed_package(tmp_path):
    code, output, calls = run(tmp_path, 'libxml2-utils', rd_apt='1',
                              simulation=f'{UPGRADE}\n{NEW}\n')
    assert code == 1
    assert 'would upgrade the installed libxml2; nothing installed' in output
    assert [c for c in calls if c.startswith('apt-get install')] == []


def test_rd_apt_upgrade_allows_it(tmp_path):
    code, output, calls = run(tmp_path, 'libxml2-utils', rd_apt='upgrade',
                              simulation=f'{UPGRADE}\n{NEW}\n')
    assert code == 0, output
    assert calls[-1] == ('apt-get install -y -q --no-install-recommends --no-upgrade '
                         'libxml2-utils')


def test_apt_get_update_only_for_a_package_the_lists_do_not_know(tmp_path):
    code, output, calls = run(tmp_path, 'libxml2-utils', known=(), rd_apt='1')
    assert code == 0, output
    assert calls.index('apt-get update -q') < calls.index(
        'apt-get install -y -q --no-install-recommends --no-upgrade libxml2-utils')


@pytest.mark.parametrize('script', ['scripts/test.sh', 'scripts/python_env.sh',
                                    'scripts/pip_install.sh', 'scripts/demo.sh',
                                    'scripts/check_readme_install.sh'])
def test_the_other_scripts_reach_apt_only_through_system_packages(script):
    code = [line for line in (REPO / script).read_text().splitlines()
            if not line.lstrip().startswith('#')]
    system = re.compile(r'\b(apt-get|dpkg|sudo)\b|\bapt (install|update|upgrade)\b')
    assert not [line for line in code if system.search(line)]


def test_ci_asks_for_the_system_packages():
    assert 'export RD_APT="${RD_APT:-upgrade}"' in (REPO / '.ci' / 'run').read_text()


def test_linters_are_found_in_the_venv_first(tmp_path, monkeypatch):
    bin_dir = tmp_path / 'venv' / 'bin'
    bin_dir.mkdir(parents=True)
    for name in ('python', 'ament_flake8'):
        (bin_dir / name).write_text('#!/bin/sh\n')
        (bin_dir / name).chmod(0o755)
    monkeypatch.setattr(sys, 'executable', str(bin_dir / 'python'))
    monkeypatch.setenv('PATH', '/nonexistent')
    assert find_linter('ament_flake8') == str(bin_dir / 'ament_flake8')
    debs = tmp_path / 'debs'
    assert search_path(debs) == os.pathsep.join(
        [str(bin_dir), '/nonexistent', str(debs / 'root' / 'usr' / 'bin')])


# scripts/linter_packages.sh DIR runs with a PATH of only these stand-ins and the basic tools
# below, so the machine's own ament_copyright/xmllint (if any) stay out of sight. The
# apt-get stand-in "downloads" a .deb per name; the dpkg stand-in "unpacks" the linter's
# executable into the target (xmllint answers --version).
LINTER_SHIMS = dict(SHIMS, **{
    'apt-get': 'echo "apt-get $*" >> "$FAKE_LOG"; [ -n "$FAKE_NO_LISTS" ] && '
               '{ echo "E: Unable to locate package $2"; exit 100; }; '
               'if [ "$1" = download ]; then shift; for p; do : > "${p}_1.0_all.deb"; done; fi; '
               '[ "$1" = -s ] && printf "%b" "$FAKE_SIMULATION"; exit 0',
    'dpkg': 'echo "dpkg $*" >> "$FAKE_LOG"; [ "$1" = -x ] || exit 2; n="${2##*/}"; '
            'case "${n%%_*}" in python3-ament-copyright) f=ament_copyright;; '
            'python3-ament-xmllint) f=ament_xmllint;; libxml2-utils) f=xmllint;; *) exit 0;; '
            'esac; mkdir -p "$3/usr/bin" "$3/usr/lib/python3/dist-packages"; '
            'printf "#!/bin/sh\\nexit 0\\n" > "$3/usr/bin/$f"; chmod +x "$3/usr/bin/$f"',
})
TOOLS = ('bash', 'env', 'mkdir', 'rm', 'ls', 'cat', 'dirname', 'chmod', 'id', 'grep', 'awk',
         'paste')
LINTER_PACKAGES = ['python3-ament-copyright', 'python3-ament-xmllint', 'libxml2-utils',
                   'python3-ament-lint']


def run_linter_packages(tmp_path, rd_apt=None, no_lists=False):
    """Run linter_packages.sh tmp/debs with nothing on PATH but stand-ins and basic tools."""
    shims = tmp_path / 'bin'
    shims.mkdir(exist_ok=True)
    for name, body in LINTER_SHIMS.items():
        path = shims / name
        path.write_text('#!/bin/bash\n' + body + '\n')
        path.chmod(0o755)
    for tool in TOOLS:
        real = shutil.which(tool)
        if real and not (shims / tool).exists():
            (shims / tool).symlink_to(real)
    log = tmp_path / 'calls.log'
    log.write_text('')
    env = {'PATH': str(shims), 'HOME': str(tmp_path), 'FAKE_LOG': str(log),
           'FAKE_INSTALLED': '', 'FAKE_KNOWN': ' '.join(LINTER_PACKAGES),
           'FAKE_SIMULATION': '', 'FAKE_NO_LISTS': '1' if no_lists else ''}
    if rd_apt is not None:
        env['RD_APT'] = rd_apt
    debs = tmp_path / 'debs'
    done = subprocess.run([shutil.which('bash'), str(LINTER_SCRIPT), str(debs)], env=env,
                          capture_output=True, text=True, timeout=120)
    return done.returncode, done.stdout + done.stderr, log.read_text().splitlines(), debs


def test_without_rd_apt_missing_linters_are_unpacked_into_the_checkout(tmp_path, monkeypatch):
    code, output, calls, debs = run_linter_packages(tmp_path)
    assert code == 0, output
    assert calls[0] == 'apt-get download ' + ' '.join(LINTER_PACKAGES)
    assert calls[1:] == [f'dpkg -x {debs}/{p}_1.0_all.deb {debs}/root' for p in LINTER_PACKAGES]
    assert not [c for c in calls if 'install' in c or c.startswith('sudo')]
    assert 'not installed' in output
    # The linter tests find them there, with their modules and the schema catalog.
    monkeypatch.setenv('PATH', str(tmp_path / 'bin'))
    exe = find_linter('ament_copyright', debs=debs)
    assert exe == str(debs / 'root' / 'usr' / 'bin' / 'ament_copyright')
    env = linter_env(exe, debs=debs)
    assert str(debs / 'root' / 'usr' / 'lib' / 'python3' / 'dist-packages') in \
        env['PYTHONPATH'].split(os.pathsep)
    assert env['XML_CATALOG_FILES'] == str(debs / 'catalog.xml')
    assert 'file://' + str(debs / 'root' / 'usr' / 'share' / 'ament_xmllint') in \
        (debs / 'catalog.xml').read_text()
    # Unpacked once: the next run finds them and calls nothing.
    code, output, calls, _ = run_linter_packages(tmp_path)
    assert (code, calls) == (0, []), output


def test_without_apt_lists_the_download_failure_names_rd_apt(tmp_path):
    code, output, calls, debs = run_linter_packages(tmp_path, no_lists=True)
    assert code == 1
    assert [line for line in output.splitlines() if line] == [
        f'linter_packages: could not apt-get download {" ".join(LINTER_PACKAGES)} (no apt or '
        f'no package lists, {debs}/download.log); RD_APT=1 ./scripts/test.sh installs them, '
        'or source ROS 2']
    assert not (debs / 'root').exists()


def test_with_rd_apt_the_missing_linters_go_through_system_packages(tmp_path):
    code, output, calls, debs = run_linter_packages(tmp_path, rd_apt='1')
    assert code == 0, output
    assert calls[-1] == ('apt-get install -y -q --no-install-recommends --no-upgrade '
                         'python3-ament-copyright python3-ament-xmllint libxml2-utils')
    assert not [c for c in calls if 'download' in c] and not debs.exists()


def test_linters_from_elsewhere_get_no_unpacked_modules(tmp_path):
    env = linter_env(str(tmp_path / 'venv' / 'bin' / 'ament_flake8'), debs=tmp_path / 'debs')
    assert env.get('PYTHONPATH') == os.environ.get('PYTHONPATH')
    assert env.get('XML_CATALOG_FILES') == os.environ.get('XML_CATALOG_FILES')


def test_the_linter_script_only_downloads_and_unpacks():
    code = [line for line in LINTER_SCRIPT.read_text().splitlines()
            if not line.lstrip().startswith('#')]
    uses = [m.group(0) for line in code
            for m in re.finditer(r'\b(apt-get|dpkg|sudo)\b( -?\w+)?', line)]
    assert set(uses) == {'apt-get', 'apt-get download', 'dpkg -x'}
