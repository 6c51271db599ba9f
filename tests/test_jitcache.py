"""A compiled kernel's cache follows the functions it calls (``sim/jitcache.py``).

numba alone keys a cached kernel on its own file: a kernel of ``sim/lockstep_kernel.py`` would be
loaded after ``tether/failsafe.py`` changed, and run the old failsafe. Here the stamp of every kernel
holds the hash of the files its callees live in, so any edit of them compiles afresh. Shown on the
kernels' own locators (the stamp numba compares), and end to end: a cached kernel whose callee's
file changed is compiled again in a new process, and one whose callee did not is loaded.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

numba = pytest.importorskip("numba")

from sim import jitcache, kernel, lockstep_kernel  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def test_every_kernel_is_cached_where_numba_would_with_a_stamp_of_its_callees() -> None:
    assert jitcache.install() and jitcache.locators()
    for fn in (kernel.law_step, kernel.discrete, lockstep_kernel._ticks, lockstep_kernel._floored):
        loc = fn._cache._impl.locator
        assert isinstance(loc, jitcache.locators()), (fn, type(loc))
        own, callees = loc.get_source_stamp()
        assert callees == jitcache.digest() and isinstance(own, bytes)
    assert jitcache.ours(kernel.__file__) and not jitcache.ours(numba.__file__)


def test_the_stamp_changes_with_a_callees_file_and_only_then(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    callee = tmp_path / "callee.py"
    callee.write_text("def f(x):\n    return x + 1\n")
    monkeypatch.setattr(jitcache, "SOURCES", (*jitcache.SOURCES, str(callee)))
    loc = lockstep_kernel._ticks._cache._impl.locator
    before = loc.get_source_stamp()
    assert loc.get_source_stamp() == before  # nothing changed: the same stamp (the cache is loaded)
    callee.write_text("def f(x):\n    return x + 2\n")
    after = loc.get_source_stamp()
    assert after[0] == before[0] and after[1] != before[1]  # its own file the same, a callee's not
    callee.write_text("def f(x):\n    return x + 1\n")
    os.utime(callee, ns=(1, 1))  # the same content again, another stat: the same stamp
    assert loc.get_source_stamp() == before


PROBE = """
import json, sys
from pathlib import Path
mods = sys.argv[1]
sys.path.insert(0, mods)
from sim import jitcache
jitcache.ROOTS.append(Path(mods))  # the probe's modules, cached as tether's
jitcache.SOURCES = (*jitcache.SOURCES, mods + "/callee.py")
import caller
got = caller.g(1.0)
print(json.dumps({"got": got, "misses": sum(caller.g.stats.cache_misses.values()),
                  "hits": sum(caller.g.stats.cache_hits.values())}))
"""
CALLER = """
from sim import kernel
import callee
f = kernel.jit(callee.f)

@kernel.jit
def g(x):
    return f(x)
"""


def test_a_cached_kernel_is_compiled_again_when_its_callee_changes(tmp_path: Path) -> None:
    """Two modules outside the tree, tracked as tether's: ``caller.g`` calls ``callee.f``. A second
    process loads ``g`` from the cache; after ``callee.py`` changed, a third compiles ``g`` again and
    returns the new value (with numba's stamp alone it would have loaded ``g`` and returned the old)."""
    mod = tmp_path / "mods"
    mod.mkdir()
    (mod / "caller.py").write_text(CALLER)
    (mod / "callee.py").write_text("def f(x):\n    return x + 1.0\n")
    env = dict(os.environ, PYTHONPATH=str(ROOT), NUMBA_CACHE_DIR=str(tmp_path / "numba"),
               TETHER_CACHE=str(tmp_path / "tether"))

    def probe() -> dict:
        done = subprocess.run([sys.executable, "-c", PROBE, str(mod)], cwd=ROOT, env=env, capture_output=True,
                              text=True, timeout=120)
        assert done.returncode == 0, done.stderr[-3000:]
        return json.loads(done.stdout.strip().splitlines()[-1])

    first, second = probe(), probe()
    assert first["got"] == second["got"] == 2.0
    assert first["misses"] == 1 and second["misses"] == 0 and second["hits"] == 1, (first, second)
    (mod / "callee.py").write_text("def f(x):\n    return x + 5.0\n")
    third = probe()
    assert third["got"] == 6.0 and third["misses"] == 1, third
