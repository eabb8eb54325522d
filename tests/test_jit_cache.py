"""The runtime drops numba's on-disk cache when any of its sources changed (online/jit_cache.py)."""

from __future__ import annotations

import shutil

import pytest

from hapticrom.online import jit_cache, kernels, proxy

pytestmark = pytest.mark.serial


def test_the_cache_directory_is_where_numba_caches_the_kernels():
    for kernel in (kernels.step_displacement_anm, proxy.step_position):
        assert jit_cache.cache_directory() == jit_cache.Path(kernel._cache._cache_path)


def test_a_changed_source_drops_the_cache_and_an_unchanged_one_keeps_it(tmp_path):
    sources, cache = tmp_path / "online", tmp_path / "cache"
    sources.mkdir()
    for name in ("kernels.py", "proxy.py"):
        shutil.copy(jit_cache.HERE / name, sources / name)
    assert jit_cache.drop_if_stale(cache, sources)  # no stamp yet
    cached = [cache / f"proxy.step_position-10.py312.{end}" for end in ("nbi", "0.nbc")]
    other = cache / "notes.txt"
    for path in (*cached, other):
        path.write_text("x")
    assert not jit_cache.drop_if_stale(cache, sources)
    assert all(p.exists() for p in cached)
    (sources / "kernels.py").write_text((sources / "kernels.py").read_text() + "\n# edited\n")
    assert jit_cache.drop_if_stale(cache, sources)  # proxy.py unchanged: still dropped
    assert not any(p.exists() for p in cached)
    assert other.exists()  # only numba's files
    assert not jit_cache.drop_if_stale(cache, sources)


def test_the_installed_sources_match_the_stamp_after_import():
    cache = jit_cache.cache_directory()
    assert (cache / jit_cache.STAMP).read_text() == jit_cache.sources_digest()
