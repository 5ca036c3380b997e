"""`vitreoguard eyes`: render the six ground-truth eye shapes (3-D view and cross-section);
with --stl DIR, write their lower halves as printable STL phantoms (models.eyes.mesh:
watertight shells in mm, frame E, the inner surface the retina)."""
from __future__ import annotations

import matplotlib.pyplot as plt
import numpy as np

from eval.cli.args import add_eye_param, number, out_dir
from eval.cli.io import UsageError, check_out_dir, prepare_out_dir, save_figure, write_json
from eval.cli.progress import phase
from models.eyes import EYE_SHAPES, make_eye
from models.shapes.sampling import unit_sphere_grid

# the plane of each cross-section: (in-plane horizontal axis in E, label)
WALL = number(0.2, 5.0, "mm")
EDGE = number(0.05, 2.0, "mm")
_SECTION = {"staphyloma": (np.array([1.0, 0.0, 0.0]), "x (temporal)"), "detached": (np.array([0.0, 1.0, 0.0]), "y (superior)")}


def register(sub) -> None:
    p = sub.add_parser("eyes", help="render the ground-truth eye shapes to eyes.png and eyes.json")
    p.add_argument("--out", type=out_dir, default=None, help="output directory of eyes.png (required unless --stl)")
    p.add_argument("--stl", type=out_dir, default=None, metavar="DIR",
                   help="write each shape's lower half (z <= 0 in E) as a watertight STL shell in mm to DIR/<shape>.stl")
    add_eye_param(p)
    p.add_argument("--wall-mm", type=WALL, default=1.0, help=f"the STL shell's wall thickness, {WALL.range}")
    p.add_argument("--edge-mm", type=EDGE, default=0.25, help=f"the STL's facet size, {EDGE.range}")
    p.set_defaults(func=main)


def figure_eyes(params: dict | None = None):
    """2 x 6 figure: each shape (built with its `params`, make_eye's keyword parameters per
    shape; None: the defaults) as a surface coloured by its departure from its base
    ellipsoid, and its cross-section through the visual axis (and the pathology)."""
    fig = plt.figure(figsize=(18, 6.5))
    stats = {}
    for k, name in enumerate(EYE_SHAPES):
        eye = make_eye(name, **(params or {}).get(name, {}))
        n_t, n_p = 60, 90
        U = unit_sphere_grid(n_t, n_p)
        X = eye.surface_points(U)
        base = 1 / np.sqrt((U * U) @ (1 / eye.radii**2))[:, None] * U
        dev = np.linalg.norm(X, axis=1) - np.linalg.norm(base, axis=1)
        ax = fig.add_subplot(2, 6, k + 1, projection="3d")
        G = X.reshape(n_t, n_p, 3)
        colors = plt.cm.coolwarm(0.5 + np.clip(dev.reshape(n_t, n_p), -2.5, 2.5) / 5.0)
        ax.plot_surface(G[..., 0], G[..., 1], G[..., 2], facecolors=colors, rstride=1, cstride=1, linewidth=0, antialiased=False, shade=False)
        ax.view_init(elev=-25, azim=-60)
        ax.set_box_aspect((1, 1, 1))
        ax.set_title(name)
        ax.set_axis_off()
        axis, label = _SECTION.get(name, (np.array([1.0, 0.0, 0.0]), "x (temporal)"))
        t = np.linspace(0, 2 * np.pi, 2000)
        D = np.outer(np.cos(t), axis) + np.outer(np.sin(t), [0.0, 0.0, 1.0])
        S = eye.surface_points(D)
        Sb = D / np.sqrt((D * D) @ (1 / eye.radii**2))[:, None]
        ax2 = fig.add_subplot(2, 6, 7 + k)
        ax2.plot(Sb @ axis, Sb[:, 2], "k--", lw=0.8, label="base ellipsoid")
        ax2.plot(S @ axis, S[:, 2], color="tab:red", lw=1.5, label=name)
        ax2.axhline(eye.anterior_z_mm - 5.0, color="gray", lw=0.6, ls=":", label="anterior crop")
        ax2.set_aspect("equal")
        ax2.set_xlabel(f"{label} mm")
        ax2.set_ylabel("z (anterior) mm")
        ax2.grid(alpha=0.3)
        if k == 0:
            ax2.legend(fontsize=7, loc="upper right")
        stats[name] = {"params": dict((params or {}).get(name, {})), "radii_mm": eye.radii.tolist(),
                       "max_inward_mm": float(-dev.min()), "max_outward_mm": float(dev.max())}
    fig.suptitle("Ground-truth retinas in E (colour: radial departure from the base ellipsoid, red = outward)")
    fig.tight_layout()
    return fig, stats


def shape_params(pairs) -> dict:
    """Per shape, the --eye-param pairs it takes (models.eyes.EYE_PARAMS); UsageError on a
    name no shape takes, or a value a shape refuses."""
    from eval.cli.args import eye_params
    from models.eyes import EYE_PARAMS

    known = {name for ps in EYE_PARAMS.values() for name in ps}
    unknown = sorted({name for name, _ in pairs} - known)
    if unknown:
        raise UsageError(f"--eye-param {unknown[0]}: no shape takes it; shapes take " + ", ".join(sorted(known)))
    return {shape: eye_params([(n, v) for n, v in pairs if n in EYE_PARAMS.get(shape, {})], shape) for shape in EYE_SHAPES}


def write_stl(folder, params: dict, wall_mm: float, edge_mm: float) -> list:
    """Write DIR/<shape>.stl for the six shapes (lower-half shells); returns the paths."""
    import trimesh

    from eval.cli.io import write_atomic
    from models.eyes.mesh import lower_half_shell

    paths = []
    for name in EYE_SHAPES:
        mesh = lower_half_shell(make_eye(name, **params[name]), wall_mm, edge_mm)
        data = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).export(file_type="stl")
        paths.append(write_atomic(folder / f"{name}.stl", data))
    return paths


def main(args) -> int:
    if args.out is None and args.stl is None:
        raise UsageError("give --out (eyes.png) or --stl DIR (STL phantoms), or both")
    params = shape_params(args.eye_param)
    for path in (args.stl, args.out):  # both checked before either is made
        if path is not None:
            check_out_dir(path)
    folder = None if args.stl is None else prepare_out_dir(args.stl)
    out = None if args.out is None else prepare_out_dir(args.out)
    if folder is not None:
        with phase("meshing the six lower halves"):
            paths = write_stl(folder, params, args.wall_mm, args.edge_mm)
        print(f"wrote {len(paths)} STL files to {folder} (mm, eye frame E; inner surface = retina)")
        if out is None:
            return 0
    with phase("rendering the six eye shapes"):
        fig, stats = figure_eyes(params)
    write_json(out / "eyes.json", stats)
    save_figure(fig, out / "eyes.png")
    print(f"wrote {out / 'eyes.png'} and {out / 'eyes.json'}")
    return 0
