"""Generated worlds kept on disk (shared.sim.world_cache), with real generation and real files."""

import json
import logging
import subprocess
import sys
import threading

import pytest

from shared.sim import world as world_module
from shared.sim import world_cache
from shared.sim.world import _cached_world, load_world, procedural_world

SEED = 4242
NAME = f"procedural:{SEED}"


@pytest.fixture
def cache(tmp_path, monkeypatch):
    """An empty cache folder of this test's; load_world's in-memory cache emptied before and after."""
    root = tmp_path / "cache"
    monkeypatch.setenv(world_cache.CACHE_DIR_ENV, str(root))
    monkeypatch.setattr(world_cache, "_unwritable", set())
    _cached_world.cache_clear()
    yield root
    _cached_world.cache_clear()


def _refuse_generation(monkeypatch):
    def refused(seed):
        raise AssertionError(f"procedural:{seed} was generated, not read from the cache")

    monkeypatch.setattr(world_module, "procedural_world", refused)


def test_a_generated_world_is_read_back_from_disk_by_a_later_process(cache, monkeypatch):
    fresh = procedural_world(SEED)
    assert load_world(NAME) == fresh
    path = world_cache.cache_path(cache, NAME)
    assert path.is_file() and path.parent.name == world_cache.generator_fingerprint()
    _cached_world.cache_clear()  # what a new process starts with
    _refuse_generation(monkeypatch)
    assert load_world("procedural:04242") == fresh  # the canonical name's file, every field equal


def test_off_keeps_nothing(cache, monkeypatch):
    monkeypatch.setenv(world_cache.CACHE_DIR_ENV, "off")
    assert world_cache.cache_root() is None
    assert load_world(NAME) == procedural_world(SEED)
    assert not cache.exists()


@pytest.mark.parametrize("damage", ["truncated", "edited", "other world", "not json", "huge", "nan extent",
                                    "integer beyond a float", "file world"])
def test_a_damaged_file_is_generated_anew_and_replaced(cache, caplog, damage):
    fresh = load_world(NAME)
    path = world_cache.cache_path(cache, NAME)
    text = path.read_text()
    doc = json.loads(text)
    if damage == "truncated":
        path.write_text(text[: len(text) // 2])
    elif damage == "edited":  # an obstacle moved without the checksum following
        doc["world"]["mjcf"] = doc["world"]["mjcf"].replace('pos="', 'pos="1', 1)
        path.write_text(json.dumps(doc))
    elif damage == "other world":  # a whole, valid file of another seed under this name
        other = procedural_world(SEED + 1)
        path.write_text(world_cache._encode(world_module._world_fields(other)))
    elif damage == "not json":
        path.write_bytes(b"\xff\xfe" + bytes(range(256)))
    elif damage == "huge":
        path.write_text(" " * (world_cache.MAX_FILE_BYTES + 1))
    else:  # whole files, checksums right, values wrong
        if damage == "nan extent":
            doc["world"]["extent"][0] = float("nan")
        elif damage == "integer beyond a float":  # float() of it raised OverflowError out of load_world
            doc["world"]["extent"][0] = 10**400
        else:
            doc["world"]["kind"] = "file"
        doc["sha256"] = world_cache._checksum(doc["world"])
        path.write_text(json.dumps(doc))
    _cached_world.cache_clear()
    with caplog.at_level(logging.WARNING, logger=world_cache.__name__):
        assert load_world(NAME) == fresh
    assert any("cannot be used" in r.getMessage() and str(path) in r.getMessage() for r in caplog.records)
    assert json.loads(path.read_text()) == json.loads(world_cache._encode(world_module._world_fields(fresh)))  # replaced by a good one


def test_an_unwritable_cache_is_said_once_and_worlds_still_load(cache, caplog):
    cache.parent.mkdir(parents=True, exist_ok=True)
    cache.write_text("a file where the cache folder should be")
    with caplog.at_level(logging.WARNING, logger=world_cache.__name__):
        assert load_world(NAME) == procedural_world(SEED)
        assert load_world(f"procedural:{SEED + 1}") == procedural_world(SEED + 1)
    said = [r.getMessage() for r in caplog.records]
    assert len(said) == 1 and "cannot be written" in said[0] and str(cache) in said[0], said


def test_writers_with_one_process_id_do_not_collide(cache, caplog, monkeypatch):
    # containers sharing the cache folder have the same process ids: one temporary name per writer, or
    # one writer truncates the file another is renaming into place (a reader sees half a world)
    import shared.files

    renamed: list[str] = []
    replace = shared.files.os.replace

    def recorded(src, dst):
        renamed.append(str(src))
        return replace(src, dst)

    monkeypatch.setattr(shared.files.os, "replace", recorded)
    world = procedural_world(SEED)
    path = world_cache.cache_path(cache, NAME)
    for _ in range(40):
        path.unlink(missing_ok=True)
        start = threading.Barrier(3)

        def write():
            start.wait()
            world_cache.cached_world(NAME, lambda: world, world_module._world_fields, world_module._world_from_fields)

        writers = [threading.Thread(target=write) for _ in range(3)]
        with caplog.at_level(logging.WARNING, logger=world_cache.__name__):
            for t in writers:
                t.start()
            for t in writers:
                t.join()
    assert not caplog.records and not world_cache._unwritable
    assert len(set(renamed)) == len(renamed) > 40  # some rounds had writers side by side, each its own name
    assert load_world(NAME) == world and not list(path.parent.glob(".*"))  # no temporary file left


def test_the_fingerprint_reads_every_module_generation_imports():
    # the generator reaches beyond shared/sim (the depth gate in shared/depth.py decides which starts
    # are kept): a change to any module it imports must change the fingerprint
    loaded = subprocess.run(
        [sys.executable, "-c", "import sys, shared.sim.world as w; w.procedural_world(3); "
         "print('\\n'.join(m.__file__ for n, m in sys.modules.items() if n.startswith('shared') and m.__file__))"],
        capture_output=True, text=True, check=True, timeout=120).stdout.split()
    sources = {str(p) for p in world_cache.generator_sources()}
    assert any(f.endswith("depth.py") for f in loaded)
    assert [f for f in loaded if f not in sources] == []


def test_the_fingerprint_follows_every_byte_of_the_generator_and_the_libraries(tmp_path):
    source = tmp_path / "world.py"
    source.write_text("x = 1\n")
    before = world_cache.fingerprint_of([source], "mujoco 3 numpy 2")
    assert world_cache.fingerprint_of([source], "mujoco 3 numpy 2") == before
    assert world_cache.fingerprint_of([source], "mujoco 4 numpy 2") != before
    source.write_text("x = 2\n")
    assert world_cache.fingerprint_of([source], "mujoco 3 numpy 2") != before


def test_the_cache_follows_the_environment(monkeypatch, tmp_path):
    monkeypatch.delenv(world_cache.CACHE_DIR_ENV, raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert world_cache.cache_root() == tmp_path / "cogexplore"
    monkeypatch.setenv("XDG_CACHE_HOME", "relative")  # the XDG spec: ignored
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert world_cache.cache_root() == tmp_path / "home" / ".cache" / "cogexplore"
    monkeypatch.setenv("HOME", "")  # not the filesystem's root
    assert world_cache.cache_root() is None
