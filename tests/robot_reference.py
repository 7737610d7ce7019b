"""Independent reference MLE of an arm seen through mirrors (docs/formats.md "Robot arms: joint states and
mounts"): scipy.optimize.least_squares over the whitened residuals, its covariance the inverse Fisher
information, in the uncertainty convention. Forward kinematics from yourdfpy (not Pinocchio), the rest in
numpy; imports nothing from mirror_fg: it reads the dataset@1 dictionary and the URDF itself.

Model: in an image with joints q (+ offsets delta), the camera's pose in {B} is C = F_c(q) M_c, the
target's D = F_t(q) M_t; a target point p goes to x = D p, through each reflection of the image in order
x <- x - 2 n (n.x - d) (the plane n.x = d fixed in {B}, v = d n; Hesch et al. eq. 3), into the camera
x_c = C^-1 x, then z = (x1/x3, x2/x3), pixels K z (eq. 9). Residuals (pixels - observed) / pixel_sigma;
each offset's prior delta / sigma.

Parameters, re-centred at the optimum so that their covariance *is* the convention's: per unknown mount
``[dtheta, dt]`` with R = Exp(dtheta) R0 (about the link's axes), t = t0 + dt; per plane dv with
v = v0 + dv; per offset its value. The Jacobian by central differences.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import yourdfpy
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation


@dataclass
class Reference:
    """The reference MLE: mounts ``{role: (R, t)}`` (roles ``camera`` or ``camera:NAME``, ``target``), planes ``{config: v}``, offsets (radians),
    covariance of all parameters (mount blocks [dtheta, dt], plane blocks of v, offsets), and its layout."""

    mounts: dict
    planes: dict
    offsets: np.ndarray
    covariance: np.ndarray
    layout: dict
    cost: float


def _exp(w):
    return Rotation.from_rotvec(w).as_matrix()


class ArmModel:
    """The model above for a dataset@1 dictionary whose URDF is at ``urdf_path``; with several cameras
    (``cameras``, ``mounts.cameras``) each image's camera has its own mount, role ``camera:NAME``."""

    def __init__(self, dataset: dict, urdf_path: str):
        self.urdf = yourdfpy.URDF.load(urdf_path, build_scene_graph=True, load_meshes=False)
        self.base = dataset["robot"].get("base_link", "base_link")
        mounts = dict(dataset.get("mounts", {}))
        # several cameras (dataset "cameras", "mounts.cameras"): a mount "camera:NAME" per camera
        cameras = {f"camera:{n}": e for n, e in mounts.pop("cameras", {}).items()}
        self.roles = [*cameras, "target"] if cameras else ["camera", "target"]
        mounts.update(cameras)
        self.links = {r: mounts.get(r, {}).get("link", self.base) for r in self.roles}
        self.unknown = [r for r in self.roles if r in mounts and
                        ("T_link_target" if r == "target" else "T_link_cam") not in mounts[r]]
        self.offset_names = list(dataset["robot"].get("joint_offsets", {}).get("estimate", []))
        self.offset_sigma = np.radians(dataset["robot"].get("joint_offsets", {}).get("prior_sigma_deg", 2.0))
        intrinsics = ({f"camera:{n}": c for n, c in dataset["cameras"].items()} if cameras
                      else {"camera": dataset["camera"]})
        self.K = {r: np.array([[c["fx"], 0, c["cx"]], [0, c["fy"], c["cy"]], [0, 0, 1.0]]) for r, c in intrinsics.items()}
        self.sigma = float(dataset["pixel_sigma"])
        fiducials = dataset["fiducials"]
        self.images = []
        for image in dataset["images"]:
            names = list(image["observations"])
            self.images.append((image["joints"], image["mirror_configs"][0],
                                np.array([fiducials[n] for n in names]).T,
                                np.array([image["observations"][n] for n in names]),
                                f"camera:{image['camera']}" if cameras else "camera"))
        self.configs = sorted({im[1] for im in self.images})

    def _fk(self, joints: dict, link: str) -> np.ndarray:
        if link == self.base:
            return np.eye(4)
        self.urdf.update_cfg(joints)
        return self.urdf.get_transform(link, self.base)

    def layout(self) -> dict:
        out, k = {}, 0
        for role in self.unknown:
            out[role] = slice(k, k + 6)
            k += 6
        for c in self.configs:
            out[c] = slice(k, k + 3)
            k += 3
        out["offsets"] = slice(k, k + len(self.offset_names))
        return out

    def unpack(self, x, start):
        layout = self.layout()
        mounts = {}
        for role in self.roles:
            R0, t0 = start["mounts"][role]
            if role in self.unknown:
                d = x[layout[role]]
                mounts[role] = (_exp(d[:3]) @ R0, t0 + d[3:])
            else:
                mounts[role] = (R0, t0)
        planes = {c: start["planes"][c] + x[layout[c]] for c in self.configs}
        return mounts, planes, x[layout["offsets"]]

    def residuals(self, x, start):
        mounts, planes, offsets = self.unpack(x, start)
        out = []
        for joints, config, points, observed, camera in self.images:
            q = dict(joints)
            for name, d in zip(self.offset_names, offsets):
                q[name] = q[name] + d
            Fc, Ft = self._fk(q, self.links[camera]), self._fk(q, self.links["target"])
            Rc, tc = Fc[:3, :3] @ mounts[camera][0], Fc[:3, :3] @ mounts[camera][1] + Fc[:3, 3]
            Rt, tt = Ft[:3, :3] @ mounts["target"][0], Ft[:3, :3] @ mounts["target"][1] + Ft[:3, 3]
            x_B = Rt @ points + tt[:, None]
            v = planes[config]
            n, d = v / np.linalg.norm(v), np.linalg.norm(v)
            x_B = x_B - 2.0 * np.outer(n, n @ x_B - d)
            x_c = Rc.T @ (x_B - tc[:, None])
            pix = (self.K[camera] @ (x_c / x_c[2]))[:2].T
            out.append(((pix - observed) / self.sigma).ravel())
        out.append(offsets / self.offset_sigma)
        return np.concatenate(out)


def reference_mle(dataset: dict, urdf_path: str, start_mounts: dict, start_planes: dict,
                  start_offsets: np.ndarray | None = None) -> Reference:
    """The MLE from ``start`` (e.g. the truth), re-centred at the optimum for the covariance."""
    model = ArmModel(dataset, urdf_path)
    start = {"mounts": dict(start_mounts), "planes": dict(start_planes)}
    size = 6 * len(model.unknown) + 3 * len(model.configs) + len(model.offset_names)
    x0 = np.zeros(size)
    if start_offsets is not None:
        x0[model.layout()["offsets"]] = start_offsets
    for _ in range(2):  # solve, re-centre at the optimum, solve again (a step of nothing)
        fit = least_squares(model.residuals, x0, args=(start,), jac="3-point", x_scale="jac", xtol=1e-14,
                            ftol=1e-14, gtol=1e-14, method="lm")
        mounts, planes, offsets = model.unpack(fit.x, start)
        start = {"mounts": mounts, "planes": planes}
        x0 = np.zeros(size)
        x0[model.layout()["offsets"]] = offsets
    r0 = model.residuals(x0, start)
    step = 1e-6
    J = np.column_stack([(model.residuals(x0 + step * e, start) - model.residuals(x0 - step * e, start)) / (2 * step)
                         for e in np.eye(size)])
    covariance = np.linalg.inv(J.T @ J)
    return Reference(mounts, planes, offsets, covariance, model.layout(), 0.5 * float(r0 @ r0))
