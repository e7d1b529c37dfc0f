"""Sensor frames of a robot: a URDF kinematic tree (pytorch-kinematics) plus static transforms.

A :class:`FrameTree` answers "where is frame ``source`` in frame ``target``" as a 4x4
homogeneous transform ``T_target_source`` (it maps ``source`` coordinates to ``target``
coordinates: ``p_target = T[:3, :3] @ p_source + T[:3, 3]``). The transforms are float64
torch tensors built by differentiable ops, so gradients reach the joint values (e.g. a
pan-tilt head whose angles come from ``sensor_msgs/JointState``).

Two sources of frames, usable together:

* a URDF: pytorch-kinematics builds the chain and runs its batched forward kinematics over
  fixed, revolute / continuous and prismatic joints. The joint origins are converted here in
  float64 (URDF ``rpy`` is fixed-axis roll, pitch, yaw: ``R = Rz(yaw) Ry(pitch) Rx(roll)``),
  because pytorch-kinematics' own URDF loader rounds them through float32 (~1e-7).
* static transforms (the YAML fallback, or frames a URDF lacks): ``parent``, ``child``,
  ``xyz`` (m) and either ``rpy`` (rad, as in a URDF) or ``quaternion_xyzw`` (ROS order).
  A child may hang below a URDF link or below another static frame.

Example:
    >>> tree = FrameTree.from_transforms(
    ...     [StaticTransform.from_xyz_rpy("base_link", "gps", [0.1, 0.0, 1.2], [0, 0, 0])]
    ... )
    >>> tree.transform("base_link", "gps")[:3, 3].tolist()
    [0.1, 0.0, 1.2]
"""

from __future__ import annotations

__all__ = ["StaticTransform", "FrameTree", "rpy_matrix", "inverse_transform"]

import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import pytorch_kinematics as pk
import torch

from msf_torch.geometry.quaternion import quat_to_matrix, xyzw_to_wxyz
from msf_torch.geometry.so3 import rpy_matrix


def _homogeneous(rotation: torch.Tensor, translation: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) and (..., 3) -> (..., 4, 4)."""
    top = torch.cat((rotation, translation[..., None]), -1)
    bottom = torch.zeros(*top.shape[:-2], 1, 4, dtype=top.dtype, device=top.device)
    bottom[..., 0, 3] = 1.0
    return torch.cat((top, bottom), -2)


def inverse_transform(transform: torch.Tensor) -> torch.Tensor:
    """Inverse of rigid transforms (..., 4, 4): ``[R^T, -R^T t]``."""
    rot_t = transform[..., :3, :3].mT
    return _homogeneous(rot_t, -(rot_t @ transform[..., :3, 3:])[..., 0])


@dataclass(frozen=True)
class StaticTransform:
    """A fixed transform ``T_parent_child``: the child frame's pose in its parent.

    Attributes:
        parent, child: frame names.
        matrix: (4, 4) float64 tensor.
    """

    parent: str
    child: str
    matrix: torch.Tensor

    @classmethod
    def from_xyz_rpy(
        cls, parent: str, child: str, xyz: Sequence[float], rpy: Sequence[float]
    ) -> StaticTransform:
        """From a translation (m) and URDF roll-pitch-yaw (rad)."""
        rot = rpy_matrix(torch.as_tensor([float(x) for x in rpy], dtype=torch.float64))
        pos = torch.as_tensor([float(x) for x in xyz], dtype=torch.float64)
        return cls(parent, child, _homogeneous(rot, pos))

    @classmethod
    def from_xyz_quaternion(
        cls, parent: str, child: str, xyz: Sequence[float], quaternion_xyzw: Sequence[float]
    ) -> StaticTransform:
        """From a translation (m) and a unit quaternion in ROS order ``[x, y, z, w]``."""
        quat = torch.as_tensor([float(x) for x in quaternion_xyzw], dtype=torch.float64)
        rot = quat_to_matrix(xyzw_to_wxyz(quat))
        pos = torch.as_tensor([float(x) for x in xyz], dtype=torch.float64)
        return cls(parent, child, _homogeneous(rot, pos))


def _origin_matrix(origin) -> torch.Tensor:
    """A URDF ``<origin>`` (parsed; may be None) as a float64 (1, 4, 4)."""
    xyz = [0.0, 0.0, 0.0] if origin is None or origin.xyz is None else list(origin.xyz)
    rpy = [0.0, 0.0, 0.0] if origin is None or origin.rpy is None else list(origin.rpy)
    return StaticTransform.from_xyz_rpy("", "", xyz, rpy).matrix[None]


_JOINT_TYPES = {
    "fixed": "fixed",
    "revolute": "revolute",
    "continuous": "revolute",
    "prismatic": "prismatic",
}
"""URDF joint type -> pytorch-kinematics joint type."""


def _chain_from_urdf(text: str, where: str) -> pk.Chain:
    """A float64 pytorch-kinematics chain with the joint origins converted in float64."""
    from pytorch_kinematics.urdf_parser_py.urdf import URDF
    from pytorch_kinematics.urdf_parser_py.xml_reflection import core

    problems: list[str] = []
    previous = core.on_error
    core.on_error = problems.append
    try:
        robot = URDF.from_xml_string(text)
    except Exception as err:  # the parser raises bare exceptions of many kinds
        raise ValueError(f"{where}: not a readable URDF ({err})") from None
    finally:
        core.on_error = previous
    if not robot.joints:
        raise ValueError(f"{where}: the URDF has no joints, so it defines no sensor frames")
    children = {j.child for j in robot.joints}
    roots = sorted({j.parent for j in robot.joints} - children)
    if len(roots) != 1:
        raise ValueError(f"{where}: the URDF must have one root link, found {roots}")
    by_parent: dict[str, list] = {}
    for joint in robot.joints:
        if joint.type not in _JOINT_TYPES:
            raise ValueError(
                f"{where}: joint '{joint.name}' has type '{joint.type}'; supported: "
                "fixed, revolute, continuous, prismatic"
            )
        by_parent.setdefault(joint.parent, []).append(joint)

    def build(link_name: str, joint) -> pk.Frame:
        frame = pk.Frame(link_name)
        frame.link = pk.Link(link_name)
        if joint is None:
            frame.joint = pk.Joint(dtype=torch.float64)
        else:
            limits = None
            if joint.type == "revolute" and joint.limit is not None:
                limits = (joint.limit.lower, joint.limit.upper)
            frame.joint = pk.Joint(
                joint.name,
                offset=pk.Transform3d(matrix=_origin_matrix(joint.origin), dtype=torch.float64),
                joint_type=_JOINT_TYPES[joint.type],
                axis=(1.0, 0.0, 0.0) if joint.axis is None else tuple(joint.axis),
                dtype=torch.float64,
                limits=limits,
            )
        frame.children = [build(j.child, j) for j in by_parent.get(link_name, [])]
        return frame

    return pk.Chain(build(roots[0], None), dtype=torch.float64)


class FrameTree:
    """Named frames of a robot and the transforms between them (module docstring).

    Args:
        chain: a float64 pytorch-kinematics chain (from :meth:`from_urdf`), or None.
        transforms: static transforms; each child must be new, each parent known (a URDF
            link or an earlier / later static child).
        source: a label (the URDF or YAML path) used in error messages.

    Raises:
        ValueError: a frame defined twice, a parent that is no frame, or a cycle.
    """

    def __init__(
        self,
        chain: pk.Chain | None = None,
        transforms: Sequence[StaticTransform] = (),
        *,
        source: str = "frames",
    ) -> None:
        self.chain = chain
        self.source = source
        self._static: dict[str, StaticTransform] = {}
        chain_frames = set() if chain is None else set(chain.get_frame_names(exclude_fixed=False))
        for item in transforms:
            if item.child in chain_frames or item.child in self._static:
                raise ValueError(f"{source}: frame '{item.child}' is defined twice")
            if item.child == item.parent:
                raise ValueError(f"{source}: frame '{item.child}' is its own parent")
            self._static[item.child] = item
        self._chain_frames = chain_frames
        for name in self._static:
            self._static_path(name)

    @classmethod
    def from_urdf(
        cls, urdf: str | os.PathLike[str], transforms: Sequence[StaticTransform] = ()
    ) -> FrameTree:
        """Frames of a URDF file (or of URDF text starting with ``<``), plus ``transforms``."""
        text = str(urdf)
        where = "URDF text"
        if not text.lstrip().startswith("<"):
            path = Path(urdf)
            where = str(path)
            try:
                text = path.read_text(encoding="utf-8")
            except OSError as err:
                raise ValueError(f"{path}: cannot read the URDF ({err.strerror})") from None
        return cls(_chain_from_urdf(text, where), transforms, source=where)

    @classmethod
    def from_transforms(cls, transforms: Sequence[StaticTransform]) -> FrameTree:
        """Frames from static transforms only (no URDF)."""
        return cls(None, transforms)

    @property
    def frames(self) -> list[str]:
        """All frame names (URDF links first, then static children)."""
        chain = [] if self.chain is None else self.chain.get_frame_names(exclude_fixed=False)
        static = sorted({t.parent for t in self._static.values()} - set(self._static))
        return list(dict.fromkeys([*chain, *static, *self._static]))

    @property
    def joint_names(self) -> list[str]:
        """The URDF's movable joints, in the order of a joint-value tensor's last axis."""
        return [] if self.chain is None else list(self.chain.get_joint_parameter_names())

    def joint_frame(self, joint: str) -> str | None:
        """The frame (URDF child link) that joint ``joint`` moves, or None if no such joint."""
        if self.chain is None:
            return None
        for name in self.chain.get_frame_names(exclude_fixed=False):
            if self.chain.find_frame(name).joint.name == joint:
                return name
        return None

    def _static_path(self, name: str) -> list[StaticTransform]:
        """Static transforms from the anchor (a URDF frame or a static root) down to ``name``."""
        path: list[StaticTransform] = []
        seen = {name}
        while name in self._static:
            item = self._static[name]
            path.append(item)
            name = item.parent
            if name in seen:
                raise ValueError(f"{self.source}: the static transforms form a cycle at '{name}'")
            seen.add(name)
        return path[::-1]

    def _anchor(self, frame: str) -> str:
        if frame not in self._chain_frames and frame not in self._static:
            if frame not in self.frames:
                raise ValueError(
                    f"{self.source}: unknown frame '{frame}' (known: {', '.join(self.frames)})"
                )
        path = self._static_path(frame)
        return path[0].parent if path else frame

    def joints_between(self, target: str, source: str) -> list[str]:
        """Movable joints whose values change ``T_target_source``."""
        if self.chain is None:
            return []
        moving = []
        for frame in {self._anchor(target), self._anchor(source)}:
            if frame not in self._chain_frames:
                continue
            for index in self.chain.parents_indices[self.chain.frame_to_idx[frame]].tolist():
                joint = int(self.chain.joint_indices[index])
                if joint >= 0:
                    moving.append(self.joint_names[joint])
        counts = {j: moving.count(j) for j in moving}
        return [j for j in self.joint_names if counts.get(j, 0) == 1]

    def _joint_tensor(
        self,
        joint_values: torch.Tensor | Mapping[str, torch.Tensor | float] | None,
        needed: list[str],
    ) -> torch.Tensor:
        """(..., J) joint values from a tensor or a name -> value mapping."""
        names = self.joint_names
        if isinstance(joint_values, torch.Tensor):
            if joint_values.shape[-1:] != (len(names),):
                raise ValueError(
                    f"joint values must be (..., {len(names)}) in the order {names}, got "
                    f"{tuple(joint_values.shape)}"
                )
            return joint_values
        values = dict(joint_values or {})
        missing = [j for j in needed if j not in values]
        if missing:
            raise ValueError(f"{self.source}: no value for joint(s) {', '.join(missing)}")
        unknown = [j for j in values if j not in names]
        if unknown:
            raise ValueError(
                f"{self.source}: unknown joint(s) {', '.join(unknown)} (movable: {names})"
            )
        tensors = {k: torch.as_tensor(v, dtype=torch.float64) for k, v in values.items()}
        shape = torch.broadcast_shapes(*(v.shape for v in tensors.values())) if tensors else ()
        like = next(iter(tensors.values()), torch.zeros((), dtype=torch.float64))
        columns = [
            tensors[j].expand(shape) if j in tensors else like.new_zeros(shape) for j in names
        ]
        return torch.stack(columns, -1) if columns else like.new_zeros((*shape, 0))

    def _root_transform(self, frame: str, fk: torch.Tensor | None, batch: tuple) -> torch.Tensor:
        """(..., 4, 4) pose of ``frame`` in its tree's root (the URDF root or a static root)."""
        path = self._static_path(frame)
        anchor = path[0].parent if path else frame
        if fk is not None and anchor in self._chain_frames:
            result = fk[self.chain.frame_to_idx[anchor]].reshape(*batch, 4, 4)
        else:
            result = torch.eye(4, dtype=torch.float64).expand(*batch, 4, 4)
        for item in path:
            result = result @ item.matrix.to(result)
        return result

    def root(self, frame: str) -> str:
        """The root of the tree that holds ``frame``: the URDF's root link, or the topmost
        parent of a chain of static transforms not attached to the URDF.

        Raises:
            ValueError: ``frame`` is no frame of this tree.
        """
        anchor = self._anchor(frame)
        if anchor in self._chain_frames:
            return self.chain.get_frame_names(exclude_fixed=False)[0]
        return anchor

    def transform(
        self,
        target: str,
        source: str,
        joint_values: torch.Tensor | Mapping[str, torch.Tensor | float] | None = None,
    ) -> torch.Tensor:
        """``T_target_source`` (..., 4, 4): the pose of ``source`` in ``target``.

        Args:
            target, source: frame names.
            joint_values: the movable joints' values (rad or m), a tensor (..., J) in the
                order of :attr:`joint_names`, or a mapping name -> value (scalar or (...,));
                joints that do not move ``source`` relative to ``target`` may be left out.
                None when no movable joint lies between the two frames.

        Returns:
            (..., 4, 4) float64, differentiable in ``joint_values``; (4, 4) without joints.

        Raises:
            ValueError: an unknown frame, frames in unconnected trees, a missing joint value.
        """
        if self.root(target) != self.root(source):
            raise ValueError(
                f"{self.source}: frames '{target}' and '{source}' are not connected by any "
                "chain of transforms"
            )
        needed = self.joints_between(target, source)
        fk = None
        batch: tuple = ()
        if self.chain is not None and (
            self._anchor(target) in self._chain_frames or self._anchor(source) in self._chain_frames
        ):
            th = self._joint_tensor(joint_values, needed)
            batch = tuple(th.shape[:-1])
            flat = th.reshape(math.prod(batch), th.shape[-1]).to(torch.float64)
            fk = self.chain.forward_kinematics_tensor(flat, analytical_grad=False)
        root_target = self._root_transform(target, fk, batch)
        root_source = self._root_transform(source, fk, batch)
        return inverse_transform(root_target) @ root_source
