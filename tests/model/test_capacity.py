"""The fixed-capacity contact store: keep the smallest separations, count the rest."""
import numpy as np

from hapticproxy.server.model import ContactParams, LocalModel, ToolSpec


def test_over_capacity_keeps_the_smallest_separations_and_counts_drops():
    m = LocalModel(ToolSpec.planar(1.0, 1e-2), ContactParams(), capacity=4)
    n = 10
    d = np.array([0.009, -0.002, 0.004, 0.001, -0.003, 0.007, 0.0, 0.008, 0.002, 0.006])
    keys = np.c_[np.zeros(n, int), np.arange(n), np.zeros(n, int)]
    nrm = np.tile([0.0, 1.0, 0.0], (n, 1))
    m.update(keys, np.zeros((n, 3)), nrm, d)
    kept = m.contacts().keys[:, 1].tolist()
    assert kept == [1, 3, 4, 6]                       # d = -0.002, 0.001, -0.003, 0.0, in order
    assert m.counters()["dropped"] == 6
    m.update(keys[:3], np.zeros((3, 3)), nrm[:3], d[:3])
    assert m.counters()["dropped"] == 6
    assert m.contact_count == 3


def test_default_capacity_is_64_and_configurable():
    assert LocalModel(ToolSpec.one_dof(1.0)).capacity == 64
    m = LocalModel(ToolSpec.one_dof(1.0), capacity=100)
    n = 100
    m.update(np.c_[np.zeros(n, int), np.arange(n), np.zeros(n, int)], np.zeros((n, 3)),
             np.tile([1.0, 0, 0], (n, 1)), np.linspace(0, 0.01, n))
    assert m.contact_count == 100 and m.counters()["dropped"] == 0


def test_a_thousand_reported_contacts_are_cut_to_capacity():
    m = LocalModel(ToolSpec.one_dof(1.0), capacity=64)
    n = 1000
    rng = np.random.default_rng(0)
    d = rng.uniform(-0.01, 0.01, n)
    m.update(np.c_[np.zeros(n, int), np.arange(n), np.zeros(n, int)], np.zeros((n, 3)),
             np.tile([1.0, 0, 0], (n, 1)), d)
    assert m.contact_count == 64 and m.counters()["dropped"] == 936
    kept = m.contacts().keys[:, 1]
    assert set(kept) == set(np.argsort(d, kind="stable")[:64])
    assert np.isfinite(m.step([1.0])).all()
