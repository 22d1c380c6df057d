"""SubmapStore: bit-identical round trips from memory and disk, LRU spilling under a byte budget, cleanup."""
import pytest
import torch

from gausem_core.gaussians import GaussianCloud
from gausem_core.slam.submap_store import SubmapStore, tensor_bytes


def entry(n: int, seed: int) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return {"means": torch.randn(n, 3, generator=g), "ids": torch.randint(0, 9, (n,), generator=g),
            "half": torch.randn(n, 2, generator=g).half(), "mask": torch.rand(n, generator=g) > 0.5}


def same(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> bool:
    return a.keys() == b.keys() and all(a[k].dtype == b[k].dtype and torch.equal(a[k], b[k]) for k in a)


def test_round_trip_from_memory_is_bit_identical_and_a_copy(tmp_path):
    original = entry(10, 0)
    with SubmapStore(max_bytes=10**6, cache_dir=tmp_path) as store:
        store.store(1, original)
        original["means"] += 1  # the store kept its own copy
        loaded = store.load(1)
        assert same(loaded, {**entry(10, 0)}) and not store.on_disk(1)
        loaded["means"].zero_()
        assert same(store.load(1), entry(10, 0))


def test_round_trip_from_disk_is_bit_identical_and_cloud_compatible(tmp_path):
    cloud = GaussianCloud.from_points(torch.rand(7, 3), torch.rand(7, 3), torch.rand(7, 3), torch.rand(7) + 0.1)
    with SubmapStore(max_bytes=0, cache_dir=tmp_path) as store:
        store.store("submap-0", cloud.tensors())
        assert store.on_disk("submap-0") and store.nbytes == 0
        assert store.disk_bytes == tensor_bytes(cloud.tensors())
        restored = GaussianCloud(**store.load("submap-0", device="cpu"))
        assert same(restored.tensors(), cloud.tensors())


def test_lru_spill_order_under_budget(tmp_path):
    size = tensor_bytes(entry(100, 0))
    with SubmapStore(max_bytes=2 * size, cache_dir=tmp_path) as store:
        for key in range(3):
            store.store(key, entry(100, key))
        assert [store.on_disk(k) for k in range(3)] == [True, False, False]  # the oldest went to disk
        assert store.nbytes == 2 * size and store.disk_bytes == size and len(store) == 3
        store.load(1)  # 1 becomes the most recent: 2 is now the least recently used
        store.store(3, entry(100, 3))
        assert [store.on_disk(k) for k in range(4)] == [True, False, True, False]
        assert same(store.load(0), entry(100, 0))  # reloading 0 spills the least recently used (1)
        assert [store.on_disk(k) for k in range(4)] == [False, True, True, False]
        assert all(same(store.load(k), entry(100, k)) for k in range(4))


def test_a_read_copies_and_moves_nothing(tmp_path):
    """Issue 63: the map publisher's loads of every spilled submap each period made each resident in turn, writing
    another to disk. A read leaves every entry where it is and the least recently used order as it was."""
    size = tensor_bytes(entry(100, 0))
    with SubmapStore(max_bytes=size, cache_dir=tmp_path) as store:
        for key in range(3):
            store.store(key, entry(100, key))
        files = sorted(tmp_path.rglob("*.pt"))
        read = store.read(0)
        assert same(read, entry(100, 0)) and same(store.read(2), entry(100, 2))
        read["means"].zero_()  # a copy
        assert [store.on_disk(k) for k in range(3)] == [True, True, False] and store.nbytes == size
        assert sorted(tmp_path.rglob("*.pt")) == files  # nothing written
        store.store(3, entry(100, 3))  # 2 is still the least recently used in memory
        assert [store.on_disk(k) for k in range(4)] == [True, True, True, False]
        assert same(store.read(0), entry(100, 0))


def test_evict_replace_and_errors(tmp_path):
    with SubmapStore(max_bytes=0, cache_dir=tmp_path) as store:
        store.store(0, entry(5, 0))
        store.store(0, entry(6, 1))  # replacing drops the old file
        assert len(list(store.directory.iterdir())) == 1 and same(store.load(0), entry(6, 1))
        store.evict(0)
        assert 0 not in store and len(store) == 0 and not any(store.directory.iterdir())
        with pytest.raises(KeyError, match="no entry 0"):
            store.load(0)
        with pytest.raises(ValueError, match="dict"):
            store.store(1, [torch.zeros(1)])
    with pytest.raises(ValueError, match="max_bytes"):
        SubmapStore(max_bytes=-1)


def test_close_deletes_the_cache_directory(tmp_path):
    store = SubmapStore(max_bytes=0, cache_dir=tmp_path)
    store.store(0, entry(5, 0))
    directory = store.directory
    assert directory.parent == tmp_path and any(directory.iterdir())
    store.close()
    store.close()
    assert not directory.exists() and list(tmp_path.iterdir()) == []
    with pytest.raises(ValueError, match="closed"):
        store.store(0, entry(5, 0))


def test_threads_storing_and_loading_at_once_under_a_tight_budget_lose_nothing(tmp_path):
    """The mapping worker stores and spills while a node's map publisher loads every submap: each call is atomic, so
    no entry goes missing half-spilled and every load returns what was stored."""
    import threading

    entries = {("cloud", i): {"means": torch.full((2000, 3), float(i))} for i in range(8)}
    store = SubmapStore(max_bytes=2 * tensor_bytes(entries["cloud", 0]), cache_dir=tmp_path)
    for key, tensors in entries.items():
        store.store(key, tensors)
    errors = []

    def hammer(keys, storing):
        try:
            for _ in range(60):
                for key in keys:
                    if storing:
                        store.store(key, entries[key])
                    loaded = store.load(key)
                    assert torch.equal(loaded["means"], entries[key]["means"])
        except Exception as err:  # noqa: BLE001 - reported by the assertion below
            errors.append(err)

    threads = [threading.Thread(target=hammer, args=(list(entries)[i::2], i == 0)) for i in range(2)]
    threads += [threading.Thread(target=hammer, args=(list(entries), False))]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(60)
    assert not errors, errors
    assert len(store) == 8 and all(torch.equal(store.load(key)["means"], t["means"]) for key, t in entries.items())
    store.close()
