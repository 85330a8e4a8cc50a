"""Geometry and structured quadratic hexahedral mesh of the idealised L4-L5 intervertebral disc.

The disc is an elliptic cylinder: ``width_mm`` along x (lateral, +x to the right),
``depth_mm`` along y (anterior-posterior, +y anterior) and ``height_mm`` along z (axial, +z
cranial); the bottom endplate lies at z = 0, the top endplate at z = ``height_mm``. The
nucleus pulposus is a concentric ellipse scaled by ``sqrt(nucleus_fraction)``, so that it holds
exactly ``nucleus_fraction`` of the volume (44 % in the study). The annulus fibrosus around it
is split into ``n_rings`` radial rings (lamellae groups) of equal thickness and, on each side of
the sagittal plane, into ``n_regions`` circumferential regions of equal parametric angle
(symmetric about the sagittal plane; region 0 is anterior, region ``n_regions - 1`` posterior;
ring 0 is the outer ring).

The mesh is built in the unit disc (parametric coordinates ``X, Y``) and mapped to the ellipse
by ``x = width/2 * X``, ``y = depth/2 * Y`` (an affine map, so volume fractions are kept). In
parametric coordinates a point at polar angle ``beta`` has ``X = rho cos(beta)``,
``Y = rho sin(beta)``; ``beta`` (the ellipse's parametric angle) is the circumferential
coordinate used for regions and fibre directions. The nucleus is an O-grid ("butterfly"): a
mapped rectangle in the centre whose corners lie on region boundaries near 45 degrees, and four
transition blocks out to the nucleus boundary; the annulus is a polar grid outside it. Elements
are 20-node serendipity hexahedra with the node order of CalculiX/Abaqus C3D20(R): corners 1-4
on the bottom face counter-clockwise seen from above, corners 5-8 above them, mid-edge nodes
9-12 (bottom), 13-16 (top), 17-20 (vertical edges).
"""

from __future__ import annotations

import logging
import math
from dataclasses import asdict, dataclass, field

import numpy as np

from femcal.errors import ConfigError
from femcal.fe.options import GeometryOptions

logger = logging.getLogger(__name__)

#: Natural coordinates of the 20 nodes of a C3D20 element, in CalculiX order.
HEX20_NATURAL: np.ndarray = np.array(
    [
        [-1, -1, -1],
        [1, -1, -1],
        [1, 1, -1],
        [-1, 1, -1],
        [-1, -1, 1],
        [1, -1, 1],
        [1, 1, 1],
        [-1, 1, 1],
        [0, -1, -1],
        [1, 0, -1],
        [0, 1, -1],
        [-1, 0, -1],
        [0, -1, 1],
        [1, 0, 1],
        [0, 1, 1],
        [-1, 0, 1],
        [-1, -1, 0],
        [1, -1, 0],
        [1, 1, 0],
        [-1, 1, 0],
    ],
    dtype=float,
)

#: Mesh densities by name (see :meth:`DiscGeometry.preset`); timings: docs' *Benchmarks > Open FE
#: model*.
MESH_PRESETS: dict[str, dict[str, int]] = {
    "coarse": {
        "elements_per_region": 1,
        "elements_per_ring": 1,
        "elements_core": 1,
        "elements_height": 2,
    },
    "default": {
        "elements_per_region": 2,
        "elements_per_ring": 1,
        "elements_core": 1,
        "elements_height": 2,
    },
    "fine": {
        "elements_per_region": 3,
        "elements_per_ring": 1,
        "elements_core": 1,
        "elements_height": 4,
    },
}


@dataclass(frozen=True)
class DiscGeometry(GeometryOptions):
    """Dimensions, regions and mesh density of the disc model (x lateral, y anterior-posterior,
    z the disc height): the fields of :class:`femcal.fe.options.GeometryOptions`, each checked
    against its bounds, and the mesh they make."""

    @classmethod
    def preset(cls, name: str, **overrides: float) -> DiscGeometry:
        """The geometry with a named mesh density (``"coarse"``, ``"default"``, ``"fine"``).

        Parameters
        ----------
        name : str
            Key of :data:`MESH_PRESETS`.
        **overrides
            Any other field of :class:`DiscGeometry`.
        """
        if name not in MESH_PRESETS:
            raise ConfigError(
                f"Unknown mesh preset {name!r}; expected one of {', '.join(MESH_PRESETS)}."
            )
        return cls(**{**MESH_PRESETS[name], **overrides})

    @classmethod
    def from_value(cls, value: DiscGeometry | dict | str | None) -> DiscGeometry:
        """A geometry from an instance, a preset name, or a dict (optionally with ``preset``)."""
        if value is None:
            return cls.preset("default")
        if isinstance(value, DiscGeometry):
            return value
        if isinstance(value, str):
            return cls.preset(value)
        if isinstance(value, dict):
            settings = dict(value)
            preset = settings.pop("preset", None)
            known = set(cls.__dataclass_fields__)
            unknown = sorted(set(settings) - known)
            if unknown:
                raise ConfigError(
                    f"Unknown DiscGeometry field(s) {', '.join(unknown)}; known fields: "
                    f"{', '.join(sorted(known))}."
                )
            return cls.preset(preset, **settings) if preset else cls(**settings)
        raise ConfigError(f"Cannot build a DiscGeometry from {type(value).__name__}.")

    def to_dict(self) -> dict:
        """The fields as a plain dict."""
        return asdict(self)

    @property
    def nucleus_scale(self) -> float:
        """Parametric radius of the nucleus boundary, ``sqrt(nucleus_fraction)``."""
        return math.sqrt(self.nucleus_fraction)

    @property
    def volume_mm3(self) -> float:
        """Exact volume of the elliptic cylinder, ``pi/4 * width * depth * height``."""
        return math.pi / 4.0 * self.width_mm * self.depth_mm * self.height_mm

    @property
    def centre(self) -> np.ndarray:
        """Centre of the disc, shape (3,)."""
        return np.array([0.0, 0.0, self.height_mm / 2.0])

    @property
    def reference_point(self) -> np.ndarray:
        """Load reference point, ``reference_height_mm`` above the disc centre, shape (3,)."""
        return np.array([0.0, 0.0, self.height_mm / 2.0 + self.reference_height_mm])

    def mesh(self) -> DiscMesh:
        """Generate the mesh (see :func:`build_mesh`)."""
        return build_mesh(self)


@dataclass
class DiscMesh:
    """A C3D20 mesh of the disc with its element and node sets.

    Attributes
    ----------
    geometry : DiscGeometry
    nodes : ndarray of shape (n_nodes, 3)
        Coordinates in mm.
    elements : ndarray of shape (n_elements, 20)
        0-based node indices in CalculiX C3D20 order (labels in a deck are index + 1).
    ring : ndarray of shape (n_elements,)
        Annulus ring of each element (0 = outer), -1 for nucleus elements.
    region : ndarray of shape (n_elements,)
        Circumferential region per side (0 = anterior), -1 for nucleus elements.
    beta : ndarray of shape (n_elements,)
        Parametric ellipse angle of the element centre in radians (+y anterior is pi/2).
    element_sets : dict of str to ndarray
        0-based element indices: ``"NUCLEUS"``, ``"ANNULUS"``, ``"CENTRAL"`` (central nucleus
        elements nearest mid-height, for the intradiscal pressure) and ``"A_R{ring}C{region}"``
        (1-based ring and region numbers).
    node_sets : dict of str to ndarray
        0-based node indices: ``"BOTTOM"`` (z = 0) and ``"TOP"`` (z = height).
    """

    geometry: DiscGeometry
    nodes: np.ndarray
    elements: np.ndarray
    ring: np.ndarray
    region: np.ndarray
    beta: np.ndarray
    element_sets: dict[str, np.ndarray] = field(default_factory=dict)
    node_sets: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def n_nodes(self) -> int:
        return int(self.nodes.shape[0])

    @property
    def n_elements(self) -> int:
        return int(self.elements.shape[0])

    def jacobians(self, order: int = 2) -> np.ndarray:
        """Jacobian determinants at Gauss points, shape (n_elements, order**3)."""
        points, _ = gauss_points(order)
        return element_jacobians(self.nodes, self.elements, points)

    def element_volumes(self) -> np.ndarray:
        """Element volumes in mm^3 (3x3x3 Gauss quadrature), shape (n_elements,)."""
        points, weights = gauss_points(3)
        return element_jacobians(self.nodes, self.elements, points) @ weights

    def fibre_axes(self) -> np.ndarray:
        """Local material axes of each element at its centre, shape (n_elements, 2, 3).

        Row 0 is the outward normal of the ellipse through the element centre (local x,
        "radial"), row 1 the counter-clockwise tangent seen from above (local y,
        "circumferential"); local z = x cross y is +z (axial).
        """
        a = self.geometry.width_mm / 2.0
        b = self.geometry.depth_mm / 2.0
        normal = np.stack([np.cos(self.beta) / a, np.sin(self.beta) / b], axis=1)
        normal /= np.linalg.norm(normal, axis=1, keepdims=True)
        tangent = np.stack([-normal[:, 1], normal[:, 0]], axis=1)
        zeros = np.zeros((self.n_elements, 1))
        return np.stack([np.hstack([normal, zeros]), np.hstack([tangent, zeros])], axis=1)


def gauss_points(order: int) -> tuple[np.ndarray, np.ndarray]:
    """Tensor-product Gauss-Legendre points and weights on the cube [-1, 1]^3.

    Returns
    -------
    points : ndarray of shape (order**3, 3)
    weights : ndarray of shape (order**3,)
    """
    x, w = np.polynomial.legendre.leggauss(order)
    grid = np.stack(np.meshgrid(x, x, x, indexing="ij"), axis=-1).reshape(-1, 3)
    weights = np.einsum("i,j,k->ijk", w, w, w).reshape(-1)
    return grid, weights


def hex20_shape_derivatives(points: np.ndarray) -> np.ndarray:
    """Derivatives of the 20 serendipity shape functions at natural coordinates.

    Parameters
    ----------
    points : ndarray of shape (n_points, 3)

    Returns
    -------
    ndarray of shape (n_points, 20, 3)
        ``d N_i / d xi_k``.
    """
    points = np.asarray(points, dtype=float)
    out = np.zeros((points.shape[0], 20, 3))
    for i, node in enumerate(HEX20_NATURAL):
        s = points * node  # xi_k * xi_k^(i)
        if np.all(node != 0):  # corner: 1/8 prod(1 + s_k) (sum s_k - 2)
            one = 1.0 + s
            for k in range(3):
                others = np.prod(np.delete(one, k, axis=1), axis=1)
                out[:, i, k] = node[k] / 8.0 * others * (s.sum(axis=1) + s[:, k] - 1)
        else:  # mid-edge: 1/4 (1 - xi_z^2) prod_{k != z} (1 + s_k)
            z = int(np.flatnonzero(node == 0)[0])
            bubble = 1.0 - points[:, z] ** 2
            for k in range(3):
                if k == z:
                    others = np.prod(np.delete(1.0 + s, z, axis=1), axis=1)
                    out[:, i, k] = -0.5 * points[:, z] * others
                else:
                    rest = [j for j in range(3) if j not in (k, z)][0]
                    out[:, i, k] = 0.25 * node[k] * bubble * (1.0 + s[:, rest])
    return out


def element_jacobians(nodes: np.ndarray, elements: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Jacobian determinants of C3D20 elements at natural coordinates.

    Parameters
    ----------
    nodes : ndarray of shape (n_nodes, 3)
    elements : ndarray of shape (n_elements, 20)
        0-based node indices in CalculiX order.
    points : ndarray of shape (n_points, 3)

    Returns
    -------
    ndarray of shape (n_elements, n_points)
    """
    dn = hex20_shape_derivatives(points)  # (p, 20, 3)
    coords = nodes[elements]  # (e, 20, 3)
    jac = np.einsum("pik,eij->epjk", dn, coords)  # d x_j / d xi_k
    return np.linalg.det(jac)


def _corner_angle_index(n_regions: int) -> int:
    """Region boundary (counted from anterior) used as the corner of the central block."""
    candidates = range(1, (n_regions + 1) // 2)
    return min(candidates, key=lambda k: abs(90.0 - 180.0 * k / n_regions - 45.0))


def build_mesh(geometry: DiscGeometry) -> DiscMesh:
    """Generate the structured C3D20 mesh of ``geometry``.

    Parameters
    ----------
    geometry : DiscGeometry

    Returns
    -------
    DiscMesh
        Nodes (n, 3), elements (m, 20) in CalculiX order, rings, regions and sets.
    """
    g = geometry
    points2d, quad, kinds, ij = _quads(_blocks(g))
    ring2d, region2d, beta2d = _quad_labels(g, points2d, quad, kinds, ij)
    nodes, elements = _extrude(g, points2d, quad)
    nz = g.elements_height
    ring = np.tile(ring2d, nz)
    region = np.tile(region2d, nz)
    kind_el = np.tile(kinds, nz)
    layer_el = np.repeat(np.arange(nz), len(quad))
    element_sets: dict[str, np.ndarray] = {
        "NUCLEUS": np.flatnonzero(kind_el != "annulus"),
        "ANNULUS": np.flatnonzero(kind_el == "annulus"),
    }
    middle_layers = [nz // 2] if nz % 2 else [nz // 2 - 1, nz // 2]
    element_sets["CENTRAL"] = np.flatnonzero((kind_el == "core") & np.isin(layer_el, middle_layers))
    for r in range(g.n_rings):
        for c in range(int(g.n_regions)):
            element_sets[f"A_R{r + 1}C{c + 1}"] = np.flatnonzero((ring == r) & (region == c))
    tol = 1e-9 * g.height_mm
    node_sets = {
        "BOTTOM": np.flatnonzero(np.abs(nodes[:, 2]) < tol),
        "TOP": np.flatnonzero(np.abs(nodes[:, 2] - g.height_mm) < tol),
    }
    mesh = DiscMesh(
        geometry=g,
        nodes=nodes,
        elements=elements,
        ring=ring,
        region=region,
        beta=np.tile(beta2d, nz),
        element_sets=element_sets,
        node_sets=node_sets,
    )
    logger.debug("Disc mesh: %d nodes, %d C3D20 elements", mesh.n_nodes, mesh.n_elements)
    return mesh


def _beta(h: np.ndarray, n: int, m: int) -> np.ndarray:
    """Parametric angle of half-step circumferential index ``h`` (0 at anterior, +y;
    clockwise seen from above) with ``n`` regions of ``m`` elements per side."""
    h = np.mod(np.asarray(h), 2 * (2 * n * m))
    return np.deg2rad(90.0 - 180.0 * h / (n * 2 * m))


def _blocks(g: DiscGeometry) -> list[tuple[np.ndarray, str]]:
    """The structured blocks of the unit disc: grids of parametric points (u, v, 2) with
    their kind, ``"core"`` (the central block), ``"transition"`` (its four edges out to the
    nucleus boundary) and ``"annulus"`` (a polar grid out to the rim)."""
    n, m = int(g.n_regions), int(g.elements_per_region)
    s = g.nucleus_scale
    kc = _corner_angle_index(n)
    n_circ = 2 * n * m  # elements around the circumference
    nx, ny = 2 * kc * m, (n - 2 * kc) * m  # central block
    phi_c = float(_beta(np.array(2 * kc * m), n, m))
    corner_radius = g.core_size * s
    xc, yc = corner_radius * math.cos(phi_c), corner_radius * math.sin(phi_c)
    xs = np.linspace(-xc, xc, 2 * nx + 1)
    ys = np.linspace(-yc, yc, 2 * ny + 1)

    blocks: list[tuple[np.ndarray, str]] = []
    # Central block: grid (2nx+1, 2ny+1, 2).
    central = np.stack(np.meshgrid(xs, ys, indexing="ij"), axis=-1)
    blocks.append((central, "core"))
    # Transition blocks: edge of the central block (u) to the nucleus boundary (v).
    v = np.linspace(0.0, 1.0, 2 * g.elements_core + 1)
    edges = [
        (np.stack([xs, np.full_like(xs, yc)], 1), np.arange(-2 * kc * m, 2 * kc * m + 1)),
        (
            np.stack([np.full_like(ys, xc), ys[::-1]], 1),
            np.arange(2 * kc * m, 2 * (n - kc) * m + 1),
        ),
        (
            np.stack([xs[::-1], np.full_like(xs, -yc)], 1),
            np.arange(2 * (n - kc) * m, 2 * (n + kc) * m + 1),
        ),
        (
            np.stack([np.full_like(ys, -xc), ys], 1),
            np.arange(2 * (n + kc) * m, 2 * (2 * n - kc) * m + 1),
        ),
    ]
    for edge, h in edges:
        b = _beta(h, n, m)
        arc = s * np.stack([np.cos(b), np.sin(b)], axis=1)
        grid = (1.0 - v)[None, :, None] * edge[:, None, :] + v[None, :, None] * arc[:, None, :]
        blocks.append((grid, "transition"))
    # Annulus: polar grid, h around the circumference, rho from the nucleus boundary outwards.
    n_rad = g.n_rings * g.elements_per_ring
    h = np.arange(0, 2 * n_circ + 1)
    rho = s + (1.0 - s) * np.arange(2 * n_rad + 1) / (2 * n_rad)
    b = _beta(h, n, m)
    annulus = rho[None, :, None] * np.stack([np.cos(b), np.sin(b)], axis=1)[:, None, :]
    blocks.append((annulus, "annulus"))
    return blocks


def _quads(
    blocks: list[tuple[np.ndarray, str]],
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Quadratic 8-node quads of the blocks, points shared between blocks merged.

    Returns the points (p, 2), the quads (q, 8) counter-clockwise seen from above, each
    quad's kind (q,) and its element indices (i, j) within its block (q, 2).
    """
    all_points: list[np.ndarray] = []
    quads: list[np.ndarray] = []
    kinds: list[str] = []
    quad_ij: list[tuple[int, int]] = []
    offset = 0
    for grid, kind in blocks:
        nu, nv = (grid.shape[0] - 1) // 2, (grid.shape[1] - 1) // 2
        index = np.arange(grid.shape[0] * grid.shape[1]).reshape(grid.shape[:2]) + offset
        all_points.append(grid.reshape(-1, 2))
        offset += grid.shape[0] * grid.shape[1]
        for i in range(nu):
            for j in range(nv):
                a, c = 2 * i, 2 * j
                quads.append(
                    np.array(
                        [
                            index[a, c],
                            index[a + 2, c],
                            index[a + 2, c + 2],
                            index[a, c + 2],
                            index[a + 1, c],
                            index[a + 2, c + 1],
                            index[a + 1, c + 2],
                            index[a, c + 1],
                        ]
                    )
                )
                kinds.append(kind)
                quad_ij.append((i, j))
    points = np.concatenate(all_points)
    _, first, inverse = np.unique(
        np.round(points, 9), axis=0, return_index=True, return_inverse=True
    )
    inverse = inverse.reshape(-1)
    points2d = points[first]
    quad = inverse[np.array(quads)]
    # Counter-clockwise orientation seen from above.
    corners = points2d[quad[:, :4]]
    area = 0.5 * np.sum(
        corners[:, :, 0] * np.roll(corners[:, :, 1], -1, axis=1)
        - np.roll(corners[:, :, 0], -1, axis=1) * corners[:, :, 1],
        axis=1,
    )
    flip = area < 0
    quad[flip] = quad[flip][:, [0, 3, 2, 1, 7, 6, 5, 4]]
    return points2d, quad, np.array(kinds), np.array(quad_ij)


def _quad_labels(
    g: DiscGeometry, points2d: np.ndarray, quad: np.ndarray, kinds: np.ndarray, ij: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ring and region of each quad (-1 in the nucleus) and the angle of its centre."""
    n, m = int(g.n_regions), int(g.elements_per_region)
    ring2d = np.full(len(quad), -1)
    region2d = np.full(len(quad), -1)
    is_annulus = kinds == "annulus"
    t = ij[is_annulus, 0]  # circumferential element index from anterior, clockwise
    k = ij[is_annulus, 1]  # radial element index from the nucleus boundary
    ring2d[is_annulus] = g.n_rings - 1 - k // g.elements_per_ring
    side_region = t // m
    region2d[is_annulus] = np.where(side_region < n, side_region, 2 * n - 1 - side_region)
    centre2d = points2d[quad[:, :4]].mean(axis=1)
    return ring2d, region2d, np.arctan2(centre2d[:, 1], centre2d[:, 0])


def _extrude(
    g: DiscGeometry, points2d: np.ndarray, quad: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Extrude the quads through the height: the nodes (n, 3) in mm and the C3D20 elements
    (e, 20), layer by layer (layers 0..2*nz: even ones hold corners and mid-edges, odd ones
    corners only)."""
    nz = g.elements_height
    scale = np.array([g.width_mm / 2.0, g.depth_mm / 2.0])
    xy = points2d * scale
    z = np.linspace(0.0, g.height_mm, 2 * nz + 1)
    n2 = len(points2d)
    full_id = np.arange(n2 * (2 * nz + 1)).reshape(2 * nz + 1, n2)  # [layer, point]
    elements = []
    for layer in range(nz):
        lo, mid, hi = full_id[2 * layer], full_id[2 * layer + 1], full_id[2 * layer + 2]
        elements.append(
            np.hstack(
                [
                    lo[quad[:, :4]],
                    hi[quad[:, :4]],
                    lo[quad[:, 4:]],
                    hi[quad[:, 4:]],
                    mid[quad[:, :4]],
                ]
            )
        )
    elements_full = np.vstack(elements)
    used = np.unique(elements_full)
    renumber = np.full(full_id.size, -1)
    renumber[used] = np.arange(used.size)
    layer_of, point_of = np.divmod(used, n2)
    nodes = np.column_stack([xy[point_of], z[layer_of]])
    return nodes, renumber[elements_full]
