"""A bladed-disk sector for CalculiX: disk segment + staggered, twisted blade, quadratic tets.

Run ``python examples/calculix_sector/sector.py OUT_DIR`` (needs ``pip install gmsh`` and the
``ccx`` program, Debian package ``calculix-ccx``): it meshes one sector with gmsh, writes the
CalculiX decks ``sector.inp`` (cyclic symmetry, every nodal diameter) and, with ``--full``,
``wheel.inp`` (the same mesh copied round the whole wheel, for a direct check), runs ``ccx``
on them, imports the sector results into ``OUT_DIR/model.npz`` (what
``bttsim model import sector.frd --options import.toml --out model.npz`` does) and writes
``scenario.toml`` for ``bttsim run`` / ``bttsim simulate``: a run-up through the first family's
EO 8 crossing.

Geometry (SI units; every dimension is a :class:`SectorDesign` field): a disk segment from the
bore to the rim, ``2 pi / n_blades`` wide, centred on angle 0; a blade from inside the rim to
the tip radius along +x, with a rectangular section whose chord turns from the root stagger to
the tip stagger (a ruled loft: pretwist) and thins towards the tip. The rotor frame is the
project's: +z axial (the trailing edge at larger z), rotation anticlockwise about +z. Nine
points along the tip chord's mid-thickness line, from the trailing edge, are mesh nodes (node
set ``TIP``); the excitation node is the mesh node nearest to a point on the leading edge.

The mesh is periodic (gmsh ``setPeriodic``): the nodes of the two cyclic faces match under the
sector rotation, so CalculiX's cyclic tie is node to node and the full-wheel deck is the sector
mesh copied ``n_blades`` times with the cut nodes merged.
"""

from __future__ import annotations

import argparse
import math
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

import numpy as np

#: Stiffness-proportional damping of the example, s (``zeta = pi f beta``: 0.003 on the first
#: family near 960 Hz). Written into ``import.toml``, so ``bttsim model import ... --options
#: import.toml`` gives the model this script imports.
DAMPING_BETA_S = 1e-6


@dataclass(frozen=True)
class SectorDesign:
    """Parameters of the example sector (m, rad, Pa, kg/m^3)."""

    n_blades: int = 8
    r_bore: float = 0.040
    r_rim: float = 0.100
    disk_width: float = 0.020          # axial
    blade_root_r: float = 0.097        # the blade starts inside the rim (fused)
    r_tip: float = 0.160
    chord_root: float = 0.030
    chord_tip: float = 0.026
    thick_root: float = 0.0040
    thick_tip: float = 0.0025
    stagger_root_deg: float = 55.0
    stagger_tip_deg: float = 41.5
    n_tip_nodes: int = 9
    nominal_node: int = 4
    force_span: float = 0.8            # excitation node: leading edge at this fraction of the span
    mesh_size: float = 0.006
    blade_mesh_size: float = 0.004
    young_pa: float = 200e9
    poisson: float = 0.28
    density: float = 7640.0
    n_modes_per_nd: int = 3            # families asked from ccx per nodal diameter

    @property
    def z_center(self) -> float:
        """Axial centre of the blade and disk: the tip chord's LE at z = 0, its TE at
        ``chord_tip sin(stagger_tip)`` (the project's [rotor] convention)."""
        return 0.5 * self.chord_tip * math.sin(math.radians(self.stagger_tip_deg))


def _section_points(d: SectorDesign, r: float, chord: float, thick: float, stagger_deg: float) -> np.ndarray:
    """Rectangle corners of a blade section in the plane x = r: TE at larger z."""
    eta = math.radians(stagger_deg)
    c = np.array([math.cos(eta), -math.sin(eta)])       # TE -> LE in (y, z)
    n = np.array([math.sin(eta), math.cos(eta)])        # thickness direction
    pts = [-0.5 * chord * c - 0.5 * thick * n, 0.5 * chord * c - 0.5 * thick * n,
           0.5 * chord * c + 0.5 * thick * n, -0.5 * chord * c + 0.5 * thick * n]
    return np.array([[r, p[0], p[1] + d.z_center] for p in pts])


def tip_points(d: SectorDesign) -> np.ndarray:
    """The tip nodes along the tip chord's mid-thickness line, from the TE, shape (n_tip, 3)."""
    eta = math.radians(d.stagger_tip_deg)
    s = np.linspace(-0.45, 0.45, d.n_tip_nodes) * d.chord_tip  # inside the tip face, not on its edges
    return np.column_stack([np.full_like(s, d.r_tip), s * math.cos(eta), d.z_center - s * math.sin(eta)])


def force_point(d: SectorDesign) -> np.ndarray:
    """A point on the leading edge's mid-thickness line at ``force_span`` of the span."""
    f = d.force_span
    r = d.blade_root_r + f * (d.r_tip - d.blade_root_r)
    root = _section_points(d, d.blade_root_r, d.chord_root, d.thick_root, d.stagger_root_deg)
    tip = _section_points(d, d.r_tip, d.chord_tip, d.thick_tip, d.stagger_tip_deg)
    le_root, le_tip = 0.5 * (root[1] + root[2]), 0.5 * (tip[1] + tip[2])
    p = le_root + f * (le_tip - le_root)
    p[0] = r
    return p


def mesh_sector(d: SectorDesign):
    """Mesh the sector with gmsh: returns (node ids, xyz (n, 3), C3D10 connectivity (m, 10),
    node sets dict)."""
    import gmsh

    gmsh.initialize(["-noenv"])
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add("sector")
        occ = gmsh.model.occ
        half = math.pi / d.n_blades
        z0 = d.z_center - 0.5 * d.disk_width
        outer = occ.addCylinder(0, 0, z0, 0, 0, d.disk_width, d.r_rim, angle=2 * half)
        inner = occ.addCylinder(0, 0, z0, 0, 0, d.disk_width, d.r_bore, angle=2 * half)
        disk, _ = occ.cut([(3, outer)], [(3, inner)])
        occ.rotate(disk, 0, 0, 0, 0, 0, 1, -half)
        wires = []
        for r, c, t, s in ((d.blade_root_r, d.chord_root, d.thick_root, d.stagger_root_deg),
                           (d.r_tip, d.chord_tip, d.thick_tip, d.stagger_tip_deg)):
            p = [occ.addPoint(*q) for q in _section_points(d, r, c, t, s)]
            lines = [occ.addLine(p[i], p[(i + 1) % 4]) for i in range(4)]
            wires.append(occ.addWire(lines))
        blade = occ.addThruSections(wires, makeSolid=True, makeRuled=True)
        fused, _ = occ.fuse(disk, blade)
        occ.synchronize()
        vol = fused[0][1]
        # the tip face: the plane x = r_tip; embed the tip points in it
        faces = gmsh.model.getBoundary(fused, oriented=False)
        tip_face = left = right = bore = None
        for _, f in faces:
            cx, cy, cz = occ.getCenterOfMass(2, f)
            ang = math.atan2(cy, cx)
            if abs(cx - d.r_tip) < 1e-9:
                tip_face = f
            elif abs(ang + half) < 1e-6 and gmsh.model.getType(2, f) == "Plane":
                left = f
            elif abs(ang - half) < 1e-6 and gmsh.model.getType(2, f) == "Plane":
                right = f
            elif gmsh.model.getType(2, f) == "Cylinder" and math.hypot(cx, cy) < d.r_bore * 1.01:
                bore = f
        if None in (tip_face, left, right, bore):
            raise RuntimeError("could not identify the tip, cyclic and bore faces; check the design")
        tips = [occ.addPoint(*q) for q in tip_points(d)]
        occ.synchronize()
        gmsh.model.mesh.embed(0, tips, 2, tip_face)
        c, s = math.cos(2 * half), math.sin(2 * half)
        gmsh.model.mesh.setPeriodic(2, [right], [left], [c, -s, 0, 0, s, c, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1])
        gmsh.option.setNumber("Mesh.CharacteristicLengthMax", d.mesh_size)
        blade_faces = [f for _, f in gmsh.model.getBoundary([(3, vol)], oriented=False)
                       if occ.getCenterOfMass(2, f)[0] > d.r_rim + 1e-6]
        field = gmsh.model.mesh.field
        fd = field.add("Distance")
        field.setNumbers(fd, "SurfacesList", blade_faces)
        ft = field.add("Threshold")
        field.setNumber(ft, "InField", fd)
        field.setNumber(ft, "SizeMin", d.blade_mesh_size)
        field.setNumber(ft, "SizeMax", d.mesh_size)
        field.setNumber(ft, "DistMin", 0.002)
        field.setNumber(ft, "DistMax", 0.02)
        field.setAsBackgroundMesh(ft)
        gmsh.option.setNumber("Mesh.ElementOrder", 2)
        gmsh.option.setNumber("Mesh.SecondOrderLinear", 0)
        gmsh.model.mesh.generate(3)
        tags, coords, _ = gmsh.model.mesh.getNodes()
        xyz = coords.reshape(-1, 3)
        etypes, _, enodes = gmsh.model.mesh.getElements(3, vol)
        (i,) = [k for k, t in enumerate(etypes) if t == 11]  # 10-node tetrahedron
        conn = np.asarray(enodes[i], dtype=np.int64).reshape(-1, 10)[:, [0, 1, 2, 3, 4, 5, 6, 7, 9, 8]]

        def nodes_of(dim, tag):
            return np.unique(gmsh.model.mesh.getNodes(dim, tag, includeBoundary=True)[0].astype(np.int64))

        sets = {"LEFT": nodes_of(2, left), "RIGHT": nodes_of(2, right), "BORE": nodes_of(2, bore),
                "TIP": np.array([nodes_of(0, p)[0] for p in tips], dtype=np.int64)}
    finally:
        gmsh.finalize()
    used = np.unique(conn)
    if not np.all(np.isin(sets["TIP"], used)):
        raise RuntimeError("a tip point is not a node of the volume mesh")
    keep = np.isin(tags.astype(np.int64), used)
    return tags.astype(np.int64)[keep], xyz[keep], conn, sets


def _write_mesh(path: Path, ids, xyz, conn, sets: dict) -> None:
    with open(path, "w") as fh:
        fh.write("*NODE, NSET=NALL\n")
        for i, p in zip(ids, xyz):
            fh.write(f"{i}, {p[0]:.12e}, {p[1]:.12e}, {p[2]:.12e}\n")
        fh.write("*ELEMENT, TYPE=C3D10, ELSET=SOLID\n")
        for e, row in enumerate(conn, start=1):
            fh.write(f"{e}, " + ", ".join(map(str, row)) + "\n")
        for name, nodes in sets.items():
            fh.write(f"*NSET, NSET={name}\n")
            for k in range(0, len(nodes), 8):
                fh.write(", ".join(map(str, nodes[k:k + 8])) + ",\n")


def _material(d: SectorDesign) -> str:
    return (f"*MATERIAL, NAME=STEEL\n*ELASTIC\n{d.young_pa:.6e}, {d.poisson}\n*DENSITY\n{d.density}\n"
            "*SOLID SECTION, ELSET=SOLID, MATERIAL=STEEL\n")


def write_sector_deck(d: SectorDesign, out: Path, mesh, speeds_rpm=()) -> Path:
    """``sector_mesh.inp`` + ``sector.inp``: cyclic symmetry, every nodal diameter 0..N/2.

    With ``speeds_rpm`` (ascending from 0), after the zero-speed frequency step one pair of
    steps per further speed: a linear ``*STATIC`` step with the centrifugal load
    (``CENTRIF``, omega^2 about +z) and a ``*STEP, PERTURBATION`` frequency step about that
    prestressed state (stress stiffening and spin softening; no Coriolis)."""
    ids, xyz, conn, sets = mesh
    sets = dict(sets)
    # bore nodes on the dependent cyclic face must not also be fixed ("*ERROR in cascade")
    sets["BORE"] = np.setdiff1d(sets["BORE"], sets["RIGHT"])
    _write_mesh(out / "sector_mesh.inp", ids, xyz, conn, sets)
    n = d.n_blades
    deck = ("*INCLUDE, INPUT=sector_mesh.inp\n" + _material(d) +
            "*SURFACE, NAME=SLAVE, TYPE=NODE\nRIGHT\n*SURFACE, NAME=MASTER, TYPE=NODE\nLEFT\n"
            "*TIE, NAME=CYC, CYCLIC SYMMETRY\nSLAVE, MASTER\n"
            f"*CYCLIC SYMMETRY MODEL, N={n}, NGRAPH=1, TIE=CYC\n0., 0., 0., 0., 0., 1.\n"
            "*BOUNDARY\nBORE, 1, 3\n*STEP\n*FREQUENCY, STORAGE=NO\n"
            # ccx prints every eigenvalue twice per nodal diameter: ask for twice the families
            f"{2 * d.n_modes_per_nd}\n*SELECT CYCLIC SYMMETRY MODES, NMIN=0, NMAX={n // 2}\n"
            "*NODE FILE\nU\n*END STEP\n")
    for rpm in speeds_rpm[1:]:
        w2 = (float(rpm) * np.pi / 30.0) ** 2
        deck += (f"*STEP\n*STATIC\n*DLOAD, OP=NEW\nSOLID, CENTRIF, {w2:.12e}, 0., 0., 0., 0., 0., 1.\n*END STEP\n"
                 f"*STEP, PERTURBATION\n*FREQUENCY\n{2 * d.n_modes_per_nd}\n"
                 f"*SELECT CYCLIC SYMMETRY MODES, NMIN=0, NMAX={n // 2}\n*NODE FILE\nU\n*END STEP\n")
    (out / "sector.inp").write_text(deck)
    return out / "sector.inp"


def write_wheel_deck(d: SectorDesign, out: Path, mesh, n_modes: int) -> Path:
    """``wheel.inp``: the sector mesh copied round the wheel, cut nodes merged; node
    ``id + s * stride`` is node ``id`` of sector ``s`` (merged right-face nodes take the next
    sector's left-face id)."""
    ids, xyz, conn, sets = mesh
    n = d.n_blades
    stride = int(ids.max())
    left, right = sets["LEFT"], sets["RIGHT"]
    pos = {int(i): k for k, i in enumerate(ids)}
    th = 2 * math.pi / n
    rot = np.array([[math.cos(th), -math.sin(th), 0], [math.sin(th), math.cos(th), 0], [0, 0, 1]])
    # right-face node -> the left-face node it coincides with after one sector rotation
    lxyz = xyz[[pos[int(i)] for i in left]] @ rot.T
    partner = {}
    for i in right:
        dist = np.linalg.norm(lxyz - xyz[pos[int(i)]], axis=1)
        k = int(np.argmin(dist))
        if dist[k] > 1e-9:
            raise RuntimeError("the cyclic faces' meshes do not match (periodic mesh failed)")
        partner[int(i)] = int(left[k])

    def gid(s, i):
        i = int(i)
        if i in partner:
            return partner[i] + ((s + 1) % n) * stride
        return i + s * stride

    with open(out / "wheel_mesh.inp", "w") as fh:
        fh.write("*NODE, NSET=NALL\n")
        for s in range(n):
            c, sn = math.cos(s * th), math.sin(s * th)
            for i, p in zip(ids, xyz):
                if int(i) in partner:
                    continue
                fh.write(f"{i + s * stride}, {c * p[0] - sn * p[1]:.12e}, {sn * p[0] + c * p[1]:.12e}, {p[2]:.12e}\n")
        fh.write("*ELEMENT, TYPE=C3D10, ELSET=SOLID\n")
        e = 1
        for s in range(n):
            for row in conn:
                fh.write(f"{e}, " + ", ".join(str(gid(s, i)) for i in row) + "\n")
                e += 1
        bore = sorted({gid(s, i) for s in range(n) for i in sets["BORE"]})
        fh.write("*NSET, NSET=BORE\n")
        for k in range(0, len(bore), 8):
            fh.write(", ".join(map(str, bore[k:k + 8])) + ",\n")
    deck = ("*INCLUDE, INPUT=wheel_mesh.inp\n" + _material(d) + "*BOUNDARY\nBORE, 1, 3\n*STEP\n"
            f"*FREQUENCY, STORAGE=NO\n{n_modes}\n*NODE FILE\nU\n*END STEP\n")
    (out / "wheel.inp").write_text(deck)
    return out / "wheel.inp"


def run_ccx(deck: Path, timeout_s: float = 900.0) -> Path:
    """Run ``ccx`` on ``deck`` in its folder (one thread); returns the ``.frd`` path."""
    ccx = shutil.which("ccx")
    if ccx is None:
        raise RuntimeError("ccx not found: apt-get install calculix-ccx")
    job = deck.with_suffix("")
    env = {"OMP_NUM_THREADS": "1", "CCX_NPROC_EQUATION_SOLVER": "1", "PATH": "/usr/bin:/bin"}
    res = subprocess.run([ccx, "-i", job.name], cwd=deck.parent, capture_output=True, text=True,
                         timeout=timeout_s, env=env)
    (deck.parent / f"{job.name}.log").write_text(res.stdout + res.stderr)
    if res.returncode != 0 or "*ERROR" in res.stdout:
        err = [ln for ln in res.stdout.splitlines() if "ERROR" in ln][:3]
        raise RuntimeError(f"ccx failed on {deck.name}: {' '.join(err) or res.returncode}")
    return job.with_suffix(".frd")


def write_import_options(d: SectorDesign, out: Path, *, damping_beta_s: float = DAMPING_BETA_S,
                         speeds_rpm=()) -> Path:
    """``import.toml`` for ``bttsim model import``: tip nodes by the TIP node set of the mesh,
    the excitation node nearest to the leading-edge point, the damping and (for a
    speed-dependent model, two speeds or more) the speed of each frequency step. :func:`main`
    imports with exactly these options, so the command line repeats it."""
    p = force_point(d)
    text = (f'# bttsim model import sector.frd --options import.toml --out model.npz\n'
            f'deck = "sector.inp"             # node sets and N are read from the CalculiX input\n'
            f'tip_nset = "TIP"                 # ordered from the trailing edge\n'
            f'nominal_node = {d.nominal_node}\n'
            f'force_xyz = [{p[0]:.6g}, {p[1]:.6g}, {p[2]:.6g}]   # the node nearest to this point\n'
            f'damping_beta_s = {float(damping_beta_s)!r}   # stiffness-proportional, s\n')
    if len(speeds_rpm) > 1:
        text += f'speeds_rpm = [{", ".join(repr(float(v)) for v in speeds_rpm)}]   # one per frequency step\n'
    (out / "import.toml").write_text(text)
    return out / "import.toml"


def write_scenario(d: SectorDesign, out: Path, model, *, engine_order: int = 8, family: int = 0,
                   duration_s: float = 6.0, span: float = 0.06) -> tuple[Path, float]:
    """``scenario.toml``: a run-up through the crossing of ``engine_order`` with ``family``
    (its nodal diameter ``EO mod N``, folded) at ``60 f / EO`` rpm, +-``span``; returns the
    path and the crossing speed (rpm)."""
    n = d.n_blades
    nd_force = engine_order % n
    nd = min(nd_force, n - nd_force)
    f = float(model.campbell_freq_hz[family, nd])
    rpm = 60.0 * f / engine_order
    if "speed_rad_s" in model.extra:  # a speed-dependent model: where the stiffened family meets the EO
        from bttsim_stream.model.report import campbell_crossings
        cross = [c for c in campbell_crossings(model, [engine_order]) if c.family == family]
        if cross:
            f, rpm = cross[0].freq_hz, cross[0].rpm
    z_probe = float(model.tip_ref[0, model.nominal_node, 2])
    text = (f"# {n}-blade CalculiX sector model: EO {engine_order} crosses family {family + 1} ND {nd} "
            f"({f:.2f} Hz) at {rpm:.1f} rpm\n"
            f"[rotor]\nn_blades = {n}\ntip_radius_m = {d.r_tip}\nstagger_deg = {d.stagger_tip_deg}\n"
            f"tip_chord_m = {d.chord_tip}\n"
            f'[model]\nsource = "model.npz"\n'
            f"[speed]\nstart_rpm = {rpm * (1 - span):.3f}\nend_rpm = {rpm * (1 + span):.3f}\n"
            f"duration_s = {duration_s}\n"
            f"[[excitation]]\nengine_order = {engine_order}\nnodal_diameter = {nd_force}\namplitude_n = 2.25\n"
            f"[probes]\naxial_position_m = {z_probe:.9g}\n")
    (out / "scenario.toml").write_text(text)
    return out / "scenario.toml", rpm


def main(out: Path, design: SectorDesign = SectorDesign(), *, full: bool = False,
         damping_beta_s: float = DAMPING_BETA_S, speeds_rpm=()) -> dict:
    """Mesh, write the decks, solve with ccx, import into ``model.npz`` and write
    ``scenario.toml``; returns the paths written (and ``crossing_rpm``, ``wheel_stride``).

    With ``speeds_rpm`` (ascending from 0) the model is speed-dependent (centrifugal
    prestress steps, ``bttsim model import --speeds-rpm``)."""
    from bttsim_stream.model import save_model
    from bttsim_stream.model.importers import format_report, import_model, import_model_speeds, load_import_options

    out.mkdir(parents=True, exist_ok=True)
    mesh = mesh_sector(design)
    files = {"sector_deck": write_sector_deck(design, out, mesh, speeds_rpm),
             "options": write_import_options(design, out, damping_beta_s=damping_beta_s, speeds_rpm=speeds_rpm)}
    files["sector_frd"] = run_ccx(files["sector_deck"])
    if full:
        n_modes = design.n_modes_per_nd * design.n_blades
        files["wheel_deck"] = write_wheel_deck(design, out, mesh, n_modes)
        files["wheel_frd"] = run_ccx(files["wheel_deck"])
        files["wheel_stride"] = int(mesh[0].max())
    opts = load_import_options(files["options"])  # what `bttsim model import --options import.toml` reads
    if opts.speeds_rpm:
        model, report = import_model_speeds([files["sector_frd"]], opts)
    else:
        model, report = import_model(files["sector_frd"], opts)
    print(format_report(report))
    files["model"] = out / "model.npz"
    save_model(model, files["model"])
    files["scenario"], files["crossing_rpm"] = write_scenario(design, out, model)
    files["n_nodes"] = int(mesh[0].size)
    return files


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path, help="output folder")
    ap.add_argument("--blades", type=int, default=SectorDesign.n_blades, help="number of blades (sectors)")
    ap.add_argument("--mesh-size", type=float, default=SectorDesign.mesh_size, help="disk element size, m")
    ap.add_argument("--blade-mesh-size", type=float, default=SectorDesign.blade_mesh_size,
                    help="blade element size, m")
    ap.add_argument("--full", action="store_true", help="also solve the full wheel directly (slower)")
    ap.add_argument("--speeds-rpm", default="", help="speeds of a speed-dependent model, rpm, comma-separated, "
                                                    "ascending from 0 (centrifugal prestress steps)")
    a = ap.parse_args()
    d = SectorDesign(n_blades=a.blades, mesh_size=a.mesh_size, blade_mesh_size=a.blade_mesh_size)
    files = main(a.out, d, full=a.full, speeds_rpm=tuple(float(v) for v in a.speeds_rpm.split(",") if v.strip()))
    print(f"{files['n_nodes']} nodes per sector; EO 8 crossing at {files['crossing_rpm']:.1f} rpm; wrote "
          + ", ".join(str(v) for k, v in files.items() if isinstance(v, Path)))
    print(f"next: cd {a.out} && bttsim model show model.npz && bttsim run scenario.toml --out run")
