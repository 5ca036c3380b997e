"""The filter's compiled step, assembled from its constraints' fillers.

Every constraint names a module-level compiled filler whose argument names say what it
reads (safety.constraints.base.CONTEXT); each field slot names the compiled kernel of
its distance field; a loop may add a kinematics kernel that turns joint angles into the
step's points. From these the filter's step is generated once as Python source: the
input checks, the tracking cost, one call per constraint in the given order (a
barrier's field evaluated at its group's points first), the clearance, and the QP's
screen and warm start (safety.step_core). The source is written to the project's
compiled-code folder (models.compiled_cache: one per version of the sources) and
compiled by numba with its disk cache, so the next process loads it instead of
compiling it.

The same generated step serves the filter's Python API (points given) and the closed
loop (points from the kinematics kernel, in the same compiled call).
"""
from __future__ import annotations

import hashlib
import importlib.util
import inspect
import os
import sys

import numpy as np

from models.compiled_cache import compiled_dir
from safety.constraints.base import CONTEXT, KINDS

def _importable(fn, what: str) -> tuple[str, str]:
    """(module, name) of a module-level compiled function, or ValueError."""
    py = getattr(fn, "py_func", None)
    module, name = getattr(fn, "__module__", None), getattr(py, "__name__", None)
    if py is None or module is None or getattr(sys.modules.get(module), name, None) is not fn:
        raise ValueError(f"{what} must be a module-level numba @njit function, got {fn!r}")
    return module, name


def _arguments(filler, i: int, has_group: bool, has_field: bool, id0: int) -> str:
    """The call's argument list of constraint i's filler, by its parameter names."""
    names = list(inspect.signature(filler.py_func).parameters)
    out = []
    for a in names:
        if a not in CONTEXT:
            raise ValueError(f"filler {filler.py_func.__name__}: unknown argument {a!r}; allowed: {', '.join(CONTEXT)}")
        if a in ("start", "stop") and not has_group:
            raise ValueError(f"filler {filler.py_func.__name__} reads {a!r} but its constraint has no group")
        if a in ("fh", "fg", "fu") and not has_field:
            raise ValueError(f"filler {filler.py_func.__name__} reads {a!r} but its constraint has no field")
        out.append({"sp": f"sp{i}", "start": f"s{i}", "stop": f"e{i}", "fh": f"fh{i}", "fg": f"fg{i}", "fu": f"fu{i}",
                    "id0": str(id0)}.get(a, a))
    return ", ".join(out)


def row_id_bases(constraints, capacities: dict) -> tuple[list, int]:
    """(each constraint's first row identity, the number of identities): an inequality
    constraint owns max_rows(its group's capacity) consecutive identities, in order."""
    bases, id0 = [], 0
    for c in constraints:
        bases.append(id0)
        if c.kind == "inequality":
            id0 += c.max_rows(capacities.get(c.group, 0))
    return bases, id0


def workspace_layout(n: int, m_cap: int, p_cap: int, k_cap: int) -> tuple[dict, int]:
    """({name: (start, stop, shape)}, size) of the float workspace for n joints, m_cap
    inequality rows, p_cap equality rows and k_cap points: H, c, lb, ub, G, h, A, b, point_h, point_bound."""
    parts = (("H", (n, n)), ("c", (n,)), ("lb", (n,)), ("ub", (n,)), ("G", (m_cap, n)), ("h", (m_cap,)),
             ("A", (p_cap, n)), ("b", (p_cap,)), ("point_h", (max(k_cap, 1),)),
             ("point_bound", (max(k_cap, 1),)))
    out, o = {}, 0
    for name, shape in parts:
        size = int(np.prod(shape))
        out[name] = (o, o + size, shape)
        o += size
    return out, o


def generate(constraints, groups: dict, kernels: dict, kinematics=None, capacities: dict | None = None,
             layout: tuple = (6, 0, 0, 0), port: tuple | None = None) -> str:
    """The step's Python source for `constraints` (in order), point `groups` (name ->
    index into `ranges`), field `kernels` (slot -> compiled kernel), an optional
    `kinematics` kernel (or the pair (kernel, pose kernel): (kp, q) -> (R_WI, p_WI), the
    instrument's pose alone, for the end pose of the actuator's pending motion; without
    it the kernel's own, points and all), and the workspace `layout` (n, m_cap, p_cap, k_cap): the
    constraints' params come packed in one array (spall, offsets spo), the workspace in
    one float and one int buffer (wsf, wsi), so that a step's call carries few arguments.
    `port`: (group index, index in the group) of the point whose clearance the step
    returns (the cutter interlock's), or None (NaN)."""
    capacities = capacities or {}
    imports = ["import numpy as np", "from numba import njit",
               "from safety.step_core import (ACTIVE_TOL, CFG_DAMPING, CONSTRAINT_FAULT, OK, STEP_FAULT, STEP_OPTIMAL,",
               "                              finish, input_fault, off_command, tracking_cost)"]
    slots = sorted({c.field for c in constraints if c.field is not None})
    for s in slots:
        if s not in kernels:
            raise ValueError(f"no field kernel for slot {s!r} (constraints read it)")
        imports.append("from {} import {} as K_{}".format(*_importable(kernels[s], f"field kernel of slot {s!r}"), s))
    body = []
    bases, _ = row_id_bases(constraints, capacities)
    for i, c in enumerate(constraints):
        if c.kind not in KINDS:
            raise ValueError(f"constraint {c.name!r}: kind must be one of {KINDS}, got {c.kind!r}")
        module, name = _importable(c.filler, f"filler of constraint {c.name!r}")
        imports.append(f"from {module} import {name} as F{i}")
        if c.group is not None:
            if c.group not in groups:
                raise ValueError(f"constraint {c.name!r} reads point group {c.group!r}; the step has {sorted(groups)}")
            body.append(f"    s{i}, e{i} = ranges[{groups[c.group]}, 0], ranges[{groups[c.group]}, 1]")
        if c.field is not None:
            body.append(f"    fh{i}, fg{i}, fu{i} = K_{c.field}(fp_{c.field}, P[s{i}:e{i}])")
        args = _arguments(c.filler, i, c.group is not None, c.field is not None, bases[i])
        if c.kind == "inequality":
            body += [f"    m = F{i}({args})", "    if m < 0:", f"        return _fault(active, q, CONSTRAINT_FAULT + {i}, -m)"]
        elif c.kind == "equality":
            body += [f"    p = F{i}({args})", "    if p < 0:", f"        return _fault(active, q, CONSTRAINT_FAULT + {i}, -p)"]
        else:
            body.append(f"    F{i}({args})")
        if c.reports_clearance:
            body += [f"    for r in range(s{i}, e{i}):", "        clearance = min(clearance, point_h[r])"]
    fp = "".join(f"fp_{s}, " for s in slots)
    ws, _ = workspace_layout(*layout)
    m_cap = layout[1]
    views = "\n".join(f"    {name} = wsf[{a}:{b}]" + (f".reshape({shape})" if len(shape) > 1 else "")
                      for name, (a, b, shape) in ws.items())
    views += f"\n    ids = wsi[0:{m_cap}]\n    at_bound = wsi[{m_cap}:{2 * m_cap}]\n"
    views += "".join(f"    sp{i} = spall[spo[{i}]:spo[{i + 1}]]\n" for i in range(len(constraints)))
    if port is None:
        port_line = "    port = np.nan\n"
    else:
        g, k = port
        port_line = (f"    port = point_h[ranges[{g}, 0] + {k}] if ranges[{g}, 0] + {k} < ranges[{g}, 1] else np.nan\n")
    src = "\n".join(imports) + f"""


@njit(cache=True)
def _fault(active, q, fault, detail):
    active[:] = False
    return STEP_FAULT, fault, detail, np.zeros(q.shape[0]), 0, 0, 0, np.nan, np.nan, True


@njit(cache=True)
def step(q, command, times, cfg, J_tip, J_roll, P, J, ranges, R_WI, p_WI, R_WI_end, p_WI_end, pending, spall, spo,
         {fp}active, warm, wsf, wsi):
""" + views + f"""    fault = input_fault(q, command, J_tip, P, J, times, pending, cfg)
    if fault != OK:
        return _fault(active, q, fault, 0)
    tracking_cost(J_tip, command[:3], J_roll, np.full(J_roll.shape[0], command[3]), cfg[CFG_DAMPING], H, c)
    lb[:] = -np.inf
    ub[:] = np.inf
    point_h[:] = np.inf
    point_bound[:] = np.inf
    m = 0
    p = 0
    clearance = np.inf
""" + "\n".join(body) + f"""
    code, x, n_bound = finish(H, c, lb, ub, G[:m], h[:m], A[:p], b[:p], ids[:m], active, warm, at_bound)
    off = off_command(J_tip, x, command) if code == STEP_OPTIMAL else True
""" + port_line + """    return code, OK, 0, x, m, p, n_bound, clearance, port, off
"""
    if kinematics is not None:
        kernel, pose = kinematics if isinstance(kinematics, tuple) else (kinematics, None)
        imports_k = "from {} import {} as KIN\n".format(*_importable(kernel, "kinematics kernel"))
        imports_k += "from safety.constraints.rcm import displaced\n"
        if pose is not None:
            imports_k += "from {} import {} as POSE\n".format(*_importable(pose, "pose kernel"))
        end_pose = "POSE(kp, displaced(q, pending))" if pose is not None else "KIN(kp, displaced(q, pending))[5:7]"
        src = imports_k + src + f"""

@njit(cache=True)
def step_at(q, command, times, cfg, kp, pending, spall, spo, {fp}active, warm, wsf, wsi):
    P, J, ranges, J_tip, J_roll, R_WI, p_WI, rcm_error = KIN(kp, q)
    R_WI_end, p_WI_end = R_WI, p_WI
    if pending.shape[0] > 0:  # the pose the actuator's pending motion ends in
        R_WI_end, p_WI_end = {end_pose}
    r = step(q, command, times, cfg, J_tip, J_roll, P, J, ranges, R_WI, p_WI, R_WI_end, p_WI_end, pending, spall, spo,
             {fp}active, warm, wsf, wsi)
    return r, P, ranges, J_tip, rcm_error
"""
    return src


_LOADED: dict[str, object] = {}


def assemble(constraints, groups: dict, kernels: dict, kinematics=None, capacities: dict | None = None,
             layout: tuple = (6, 0, 0, 0), port: tuple | None = None):
    """The generated module (attributes `step`, and `step_at` with kinematics) for these
    constraints, groups, field kernels, kinematics and workspace layout (generate);
    written and imported once per distinct source."""
    src = generate(constraints, groups, kernels, kinematics, capacities, layout, port)
    digest = hashlib.sha256(src.encode()).hexdigest()[:16]
    if digest in _LOADED:
        return _LOADED[digest]
    folder = compiled_dir() / "steps"
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"step_{digest}.py"
    text = f'"""Generated by safety.assembly: the filter step for {", ".join(c.name for c in constraints)}."""\n{src}'
    if not path.exists() or path.read_text() != text:
        tmp = path.with_suffix(f".{os.getpid()}.tmp")
        tmp.write_text(text)
        os.replace(tmp, path)  # atomic: parallel processes may generate the same step
    name = f"vitreoguard_step_{digest}"
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    _LOADED[digest] = module
    return module
