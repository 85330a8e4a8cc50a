"""The structured C3D20 disc mesh: element quality, volumes, sets, node order, settings."""

from __future__ import annotations

import math

import numpy as np
import pytest

from femcal.errors import ConfigError
from femcal.fe.geometry import (
    HEX20_NATURAL,
    MESH_PRESETS,
    DiscGeometry,
    element_jacobians,
    gauss_points,
    hex20_shape_derivatives,
)


@pytest.fixture(scope="module", params=sorted(MESH_PRESETS))
def mesh(request):
    return DiscGeometry.preset(request.param).mesh()


def test_shape_functions_reproduce_linear_fields():
    points = np.random.default_rng(0).uniform(-1, 1, size=(7, 3))
    dn = hex20_shape_derivatives(points)
    np.testing.assert_allclose(dn.sum(axis=1), 0.0, atol=1e-12)
    # sum_i dN_i/dxi_k * xi_i^(j) = delta_jk (isoparametric identity map)
    grad = np.einsum("pik,ij->pjk", dn, HEX20_NATURAL)
    np.testing.assert_allclose(grad, np.broadcast_to(np.eye(3), grad.shape), atol=1e-12)


def test_jacobian_of_a_scaled_reference_cube():
    nodes = HEX20_NATURAL * np.array([2.0, 3.0, 0.5])
    points, weights = gauss_points(2)
    jac = element_jacobians(nodes, np.arange(20)[None, :], points)
    np.testing.assert_allclose(jac, np.full((1, 8), 3.0))
    assert jac @ weights == pytest.approx(2 * 2.0 * 2 * 3.0 * 2 * 0.5)


def test_all_jacobians_positive(mesh):
    jac = mesh.jacobians(order=3)
    assert jac.min() > 0.0
    # no badly distorted elements: Jacobian ratio within each element
    assert (jac.min(axis=1) / jac.max(axis=1)).min() > 0.2


def test_volume_and_nucleus_fraction(mesh):
    g = mesh.geometry
    volumes = mesh.element_volumes()
    assert volumes.min() > 0
    assert volumes.sum() == pytest.approx(
        math.pi / 4 * g.width_mm * g.depth_mm * g.height_mm, rel=2e-3
    )
    nucleus = volumes[mesh.element_sets["NUCLEUS"]].sum() / volumes.sum()
    assert nucleus == pytest.approx(g.nucleus_fraction, rel=0.05)


def test_sets_partition_the_mesh(mesh):
    g = mesh.geometry
    sets = mesh.element_sets
    nucleus, annulus = set(sets["NUCLEUS"].tolist()), set(sets["ANNULUS"].tolist())
    assert not nucleus & annulus
    assert nucleus | annulus == set(range(mesh.n_elements))
    regions = [sets[f"A_R{r + 1}C{c + 1}"] for r in range(g.n_rings) for c in range(g.n_regions)]
    assert all(len(ids) > 0 for ids in regions)
    assert sorted(np.concatenate(regions).tolist()) == sorted(annulus)
    assert set(sets["CENTRAL"].tolist()) <= nucleus
    # ring 0 is outside ring n-1; region 0 is anterior (+y), the last posterior (-y)
    centres = mesh.nodes[mesh.elements[:, :8]].mean(axis=1)
    radius = np.hypot(centres[:, 0] / (g.width_mm / 2), centres[:, 1] / (g.depth_mm / 2))
    assert radius[sets["A_R1C3"]].min() > radius[sets[f"A_R{g.n_rings}C3"]].max()
    assert centres[sets["A_R1C1"], 1].min() > 0 > centres[sets[f"A_R1C{g.n_regions}"], 1].max()
    # symmetric about the sagittal plane: each region has as many elements left as right
    for ids in regions:
        assert np.sum(centres[ids, 0] > 0) == np.sum(centres[ids, 0] < 0)
    # central elements lie near the centre of the disc
    central = centres[sets["CENTRAL"]]
    assert np.abs(central[:, 2] - g.height_mm / 2).max() < g.height_mm / 2
    assert np.hypot(central[:, 0], central[:, 1]).max() < 0.5 * g.depth_mm / 2


def test_node_sets_and_node_order(mesh):
    g = mesh.geometry
    nodes, elements = mesh.nodes, mesh.elements
    np.testing.assert_allclose(nodes[mesh.node_sets["BOTTOM"], 2], 0.0, atol=1e-12)
    np.testing.assert_allclose(nodes[mesh.node_sets["TOP"], 2], g.height_mm, atol=1e-12)
    # every node belongs to an element; no duplicate nodes
    assert np.unique(elements).size == mesh.n_nodes
    assert np.unique(np.round(nodes, 6), axis=0).shape[0] == mesh.n_nodes
    # CalculiX order: corners 1-4 below 5-8, vertical mid-edge nodes 17-20 halfway between
    z = nodes[elements, 2]
    assert np.all(z[:, 4:8] > z[:, 0:4])
    np.testing.assert_allclose(z[:, 16:20], 0.5 * (z[:, 0:4] + z[:, 4:8]))
    np.testing.assert_allclose(nodes[elements[:, 16:20], :2], nodes[elements[:, 0:4], :2])
    # mid-edge nodes 9-12 lie near the middle of their edges (straight or arcs)
    corners = nodes[elements[:, [0, 1, 2, 3]]]
    mids = nodes[elements[:, 8:12]]
    chord = 0.5 * (corners + np.roll(corners, -1, axis=1))
    edge = np.linalg.norm(np.roll(corners, -1, axis=1) - corners, axis=2)
    assert (np.linalg.norm(mids - chord, axis=2) / edge).max() < 0.15


def test_fibre_axes_are_radial_and_circumferential(mesh):
    axes = mesh.fibre_axes()
    np.testing.assert_allclose(np.linalg.norm(axes, axis=2), 1.0)
    np.testing.assert_allclose(np.einsum("ei,ei->e", axes[:, 0], axes[:, 1]), 0.0, atol=1e-12)
    np.testing.assert_allclose(np.cross(axes[:, 0], axes[:, 1])[:, 2], 1.0)
    ids = mesh.element_sets["ANNULUS"]
    centres = mesh.nodes[mesh.elements[ids, :8]].mean(axis=1)
    assert np.all(np.einsum("ei,ei->e", axes[ids, 0, :2], centres[:, :2]) > 0)  # outwards


def test_presets_grow():
    counts = [DiscGeometry.preset(p).mesh().n_elements for p in ("coarse", "default", "fine")]
    assert counts == sorted(counts) and len(set(counts)) == 3


@pytest.mark.parametrize("n_regions", [3, 4, 6])
def test_other_region_counts(n_regions):
    g = DiscGeometry(n_regions=n_regions, n_rings=3, elements_height=1)
    mesh = g.mesh()
    assert mesh.jacobians().min() > 0
    assert set(mesh.region[mesh.region >= 0].tolist()) == set(range(n_regions))
    assert set(mesh.ring[mesh.ring >= 0].tolist()) == set(range(3))


@pytest.mark.parametrize(
    "settings",
    [
        {"nucleus_fraction": 1.2},
        {"width_mm": -1.0},
        {"n_regions": 2},
        {"elements_height": 0},
        {"core_size": 1.0},
    ],
)
def test_invalid_geometry(settings):
    with pytest.raises(ConfigError):
        DiscGeometry(**settings)


def test_from_value():
    assert DiscGeometry.from_value("coarse") == DiscGeometry.preset("coarse")
    g = DiscGeometry.from_value({"preset": "fine", "height_mm": 9.0})
    assert g.height_mm == 9.0 and g.elements_height == MESH_PRESETS["fine"]["elements_height"]
    assert DiscGeometry.from_value(g) is g
    with pytest.raises(ConfigError, match="Unknown DiscGeometry field"):
        DiscGeometry.from_value({"hieght_mm": 9.0})
    with pytest.raises(ConfigError, match="Unknown mesh preset"):
        DiscGeometry.preset("medium")
