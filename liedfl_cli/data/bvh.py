"""Reader for Biovision Hierarchy (BVH) motion files, Euler-angle conversion and forward kinematics.

A BVH file has two sections:

    HIERARCHY
    ROOT <name> { OFFSET x y z  CHANNELS n <ch_1> ... <ch_n>  (JOINT <name> {...} | End Site { OFFSET x y z })* }
    MOTION
    Frames: <F>
    Frame Time: <seconds>
    <F lines of sum(n) numbers, channels in hierarchy (depth-first) order>

Channels are `Xposition Yposition Zposition Xrotation Yrotation Zrotation` in any order (each at most
once per joint).  Rotation angles are in degrees; a joint's local rotation is the product of the
elementary rotations in the order the joint declares its rotation channels,

    R = R_a1(theta_1) R_a2(theta_2) R_a3(theta_3)     for channels a1rotation a2rotation a3rotation,

i.e. intrinsic rotations (scipy `Rotation.from_euler("ZYX", ...)` for `Zrotation Yrotation Xrotation`).
A joint's frame maps to its parent's frame by x_parent = t + R x_joint with the translation
t = OFFSET + (position channels, zero where absent), so world poses follow by `forward_kinematics`.
Both CRLF and LF line endings (also mixed) are accepted.  Every problem raises `DatasetError` with a
one-line message naming the file and the line (and value column) or field.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import DatasetError

ROTATION_CHANNELS = ("Xrotation", "Yrotation", "Zrotation")
POSITION_CHANNELS = ("Xposition", "Yposition", "Zposition")
CHANNEL_NAMES = POSITION_CHANNELS + ROTATION_CHANNELS
_AXIS = {"X": 0, "Y": 1, "Z": 2}
_LINE_BREAK = re.compile(r"\r\n|\r|\n")


@dataclass(eq=False)
class BVH:
    """Content of a BVH file.  Joints are numbered in file (depth-first) order, the root is joint 0."""

    names: list[str]  # joint names, (J,)
    parents: list[int]  # parent index of each joint, -1 for the root
    offsets: np.ndarray  # (J, 3) OFFSET of each joint in its parent's frame (file units)
    channels: list[tuple[str, ...]]  # channel names of each joint, in file order
    frame_time: float  # seconds between frames
    frames: np.ndarray  # (F, C) channel values, C = sum of len(channels)
    end_sites: list[tuple[int, np.ndarray]] = field(default_factory=list)  # (joint index, OFFSET (3,))
    source: str = "<string>"

    # ------------------------------------------------------------------ layout
    @property
    def n_joints(self) -> int:
        return len(self.names)

    @property
    def n_frames(self) -> int:
        return int(self.frames.shape[0])

    @property
    def n_channels(self) -> int:
        return int(sum(len(c) for c in self.channels))

    def channel_start(self, j: int) -> int:
        """Column of the first channel of joint j in `frames`."""
        return int(sum(len(c) for c in self.channels[:j]))

    def joint_index(self, name: str) -> int:
        try:
            return self.names.index(name)
        except ValueError:
            raise DatasetError(
                f"{self.source}: joint {name!r} is not in the hierarchy (joints: {', '.join(self.names)})"
            ) from None

    def rotation_order(self, j: int) -> str:
        """Axes of joint j's rotation channels in declared order, e.g. "ZYX" ("" if it has none)."""
        return "".join(c[0] for c in self.channels[j] if c in ROTATION_CHANNELS)

    # ------------------------------------------------------------------ channel values
    def euler_angles(self, j: int) -> np.ndarray:
        """(F, k) rotation-channel values of joint j in degrees, in declared order."""
        s = self.channel_start(j)
        cols = [s + i for i, c in enumerate(self.channels[j]) if c in ROTATION_CHANNELS]
        return self.frames[:, cols]

    def local_rotations(self, joints: Sequence[int] | None = None) -> np.ndarray:
        """(F, len(joints), 3, 3) local rotation matrices (all joints by default)."""
        joints = range(self.n_joints) if joints is None else joints
        out = [euler_to_matrix(self.euler_angles(j), self.rotation_order(j)) for j in joints]
        return np.stack(out, axis=1) if out else np.zeros((self.n_frames, 0, 3, 3))

    def local_translations(self, joints: Sequence[int] | None = None) -> np.ndarray:
        """(F, len(joints), 3) translation of each joint in its parent's frame: OFFSET + position channels."""
        joints = range(self.n_joints) if joints is None else joints
        out = np.zeros((self.n_frames, len(joints), 3))
        for k, j in enumerate(joints):
            out[:, k] = self.offsets[j]
            s = self.channel_start(j)
            for i, c in enumerate(self.channels[j]):
                if c in POSITION_CHANNELS:
                    out[:, k, _AXIS[c[0]]] += self.frames[:, s + i]
        return out

    def world_poses(self):
        """(R_world (F, J, 3, 3), p_world (F, J, 3)) of every joint by forward kinematics."""
        return forward_kinematics(self.parents, self.local_translations(), self.local_rotations())

    def end_site_positions(self, R_world: np.ndarray, p_world: np.ndarray) -> np.ndarray:
        """(F, n_end_sites, 3) world positions of the End Sites given the joints' world poses."""
        if not self.end_sites:
            return np.zeros(p_world.shape[:-2] + (0, 3))
        idx = [j for j, _ in self.end_sites]
        off = np.stack([o for _, o in self.end_sites])
        return p_world[..., idx, :] + np.einsum("...bij,bj->...bi", R_world[..., idx, :, :], off)

    def bone_lengths(self) -> np.ndarray:
        """(F, J) distance of each joint from its parent under forward kinematics (0 for the root)."""
        _, p = self.world_poses()
        par = np.array([max(q, 0) for q in self.parents])
        d = np.linalg.norm(p - p[:, par], axis=-1)
        d[:, [j for j, q in enumerate(self.parents) if q < 0]] = 0.0
        return d


# ---------------------------------------------------------------------- rotations and kinematics
def axis_rotation(axis: str, angle_rad: np.ndarray) -> np.ndarray:
    """(...,) angles (radians) -> (..., 3, 3) rotation about the coordinate axis 'X', 'Y' or 'Z'."""
    a = np.asarray(angle_rad, dtype=np.float64)
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    if axis == "X":
        rows = ((o, z, z), (z, c, -s), (z, s, c))
    elif axis == "Y":
        rows = ((c, z, s), (z, o, z), (-s, z, c))
    elif axis == "Z":
        rows = ((c, -s, z), (s, c, z), (z, z, o))
    else:
        raise ValueError(f"axis must be 'X', 'Y' or 'Z', got {axis!r}")
    return np.stack([np.stack(r, -1) for r in rows], -2)


def euler_to_matrix(angles_deg: np.ndarray, order: str) -> np.ndarray:
    """(..., k) angles in degrees, order of k axes (e.g. "ZYX") -> (..., 3, 3) = R_order[0] R_order[1] ...

    The BVH convention (intrinsic rotations in the declared channel order). An empty order gives I.
    """
    angles = np.asarray(angles_deg, dtype=np.float64)
    if angles.shape[-1] != len(order):
        raise ValueError(f"got {angles.shape[-1]} angles for rotation order {order!r}")
    R = np.broadcast_to(np.eye(3), angles.shape[:-1] + (3, 3)).copy()
    for i, ax in enumerate(order):
        R = R @ axis_rotation(ax, np.deg2rad(angles[..., i]))
    return R


def forward_kinematics(parents: Sequence[int], translations: np.ndarray, rotations: np.ndarray):
    """World poses of a kinematic tree.

    parents: parent index of each joint (-1 for a root; parents must precede their children).
    translations: (..., J, 3) joint origin in the parent's frame (for a root: in the world frame).
    rotations: (..., J, 3, 3) local rotations (for a root: its world rotation).
    Returns (R_world (..., J, 3, 3), p_world (..., J, 3)) with R_j = R_parent R_local_j and
    p_j = p_parent + R_parent t_j.
    """
    t = np.asarray(translations, dtype=np.float64)
    Rl = np.asarray(rotations, dtype=np.float64)
    J = len(parents)
    if t.shape[-2:] != (J, 3) or Rl.shape[-3:] != (J, 3, 3):
        raise ValueError(f"forward_kinematics: {J} joints but translations {t.shape}, rotations {Rl.shape}")
    lead = np.broadcast_shapes(t.shape[:-2], Rl.shape[:-3])
    Rw = np.empty(lead + (J, 3, 3))
    pw = np.empty(lead + (J, 3))
    for j, q in enumerate(parents):
        if q < 0:
            Rw[..., j, :, :] = Rl[..., j, :, :]
            pw[..., j, :] = t[..., j, :]
        else:
            if q >= j:
                raise ValueError(f"forward_kinematics: parent {q} of joint {j} does not precede it")
            Rw[..., j, :, :] = Rw[..., q, :, :] @ Rl[..., j, :, :]
            pw[..., j, :] = pw[..., q, :] + np.einsum("...ij,...j->...i", Rw[..., q, :, :], t[..., j, :])
    return Rw, pw


# ---------------------------------------------------------------------- parsing
class _Tokens:
    """Whitespace tokens of the HIERARCHY section with their 1-based line numbers."""

    def __init__(self, lines: list[str], start: int, source: str):
        self.lines, self.source = lines, source
        self.line_no, self.pos = start, 0
        self.items: list[str] = []
        self._fill()

    def _fill(self):
        while self.pos >= len(self.items) and self.line_no < len(self.lines):
            self.items = self.lines[self.line_no].split()
            self.pos = 0
            self.line_no += 1

    @property
    def current_line(self) -> int:
        """1-based number of the line holding the next token (the last line at the end of the file)."""
        self._fill()
        return self.line_no

    def peek(self) -> str | None:
        self._fill()
        return self.items[self.pos] if self.pos < len(self.items) else None

    def next(self, what: str) -> str:
        tok = self.peek()
        if tok is None:
            raise DatasetError(
                f"{self.source}: file is truncated: reached the end of the file while reading "
                f"{what} in the HIERARCHY section"
            )
        self.pos += 1
        return tok

    def expect(self, word: str, context: str) -> None:
        line = self.current_line
        tok = self.next(f"'{word}' ({context})")
        if tok != word:
            raise DatasetError(f"{self.source}: line {line}: expected '{word}' ({context}), found {tok!r}")

    def number(self, what: str) -> float:
        line = self.current_line
        tok = self.next(what)
        try:
            v = float(tok)
        except ValueError:
            raise DatasetError(f"{self.source}: line {line}: {what} {tok!r} is not a number") from None
        if not math.isfinite(v):
            raise DatasetError(f"{self.source}: line {line}: {what} {tok!r} is not finite")
        return v

    def rest_of_line(self) -> list[str]:
        """Remaining tokens on the line of the last consumed token (consumed; may be empty)."""
        out = self.items[self.pos :]
        self.pos = len(self.items)
        return out


def _parse_channels(tok: _Tokens, joint: str) -> tuple[str, ...]:
    line = tok.current_line
    n_text = tok.next(f"the channel count of joint {joint!r}")
    try:
        n = int(n_text)
    except ValueError:
        raise DatasetError(
            f"{tok.source}: line {line}: joint {joint!r}: CHANNELS count {n_text!r} is not an integer"
        ) from None
    if not 0 <= n <= 6:
        raise DatasetError(f"{tok.source}: line {line}: joint {joint!r}: CHANNELS count {n} must be between 0 and 6")
    chans: list[str] = []
    for _ in range(n):
        line = tok.current_line
        c = tok.next(f"the channels of joint {joint!r}")
        if c not in CHANNEL_NAMES:
            raise DatasetError(
                f"{tok.source}: line {line}: joint {joint!r}: unknown channel name {c!r} "
                f"(expected one of {', '.join(CHANNEL_NAMES)})"
            )
        if c in chans:
            raise DatasetError(
                f"{tok.source}: line {line}: joint {joint!r}: channel order {' '.join(chans + [c])} "
                f"repeats {c!r}; each channel may appear once"
            )
        chans.append(c)
    return tuple(chans)


def _parse_offset(tok: _Tokens, who: str) -> np.ndarray:
    tok.expect("OFFSET", who)
    return np.array([tok.number(f"OFFSET {ax} of {who}") for ax in "XYZ"])


def parse_bvh(text: str, source: str = "<string>") -> BVH:
    """Parse the text of a BVH file (see the module docstring). `source` names it in error messages."""
    lines = _LINE_BREAK.split(text)
    # HIERARCHY
    first = next((i for i, ln in enumerate(lines) if ln.strip()), None)
    if first is None:
        raise DatasetError(f"{source}: file is empty")
    if lines[first].split()[0] != "HIERARCHY":
        raise DatasetError(f"{source}: line {first + 1}: expected 'HIERARCHY', found {lines[first].strip()[:40]!r}")
    tok = _Tokens(lines, first + 1, source)
    line = tok.current_line
    kw: str | None = tok.next("'ROOT'")
    if kw != "ROOT":
        raise DatasetError(f"{source}: line {line}: expected 'ROOT' after HIERARCHY, found {kw!r}")

    names: list[str] = []
    parents: list[int] = []
    offsets: list[np.ndarray] = []
    channels: list[tuple[str, ...]] = []
    end_sites: list[tuple[int, np.ndarray]] = []

    def joint(parent: int) -> None:
        line = tok.current_line
        name_tokens = tok.rest_of_line()
        brace = bool(name_tokens) and name_tokens[-1] == "{"  # "JOINT name {" on one line
        name = " ".join(name_tokens[:-1] if brace else name_tokens)
        if not name:
            raise DatasetError(f"{source}: line {line}: joint has no name")
        if not brace:
            tok.expect("{", f"opening joint {name!r}")
        if name in names:
            raise DatasetError(f"{source}: line {line}: joint name {name!r} is used twice")
        j = len(names)
        names.append(name)
        parents.append(parent)
        offsets.append(_parse_offset(tok, f"joint {name!r}"))
        line = tok.current_line
        if tok.peek() == "CHANNELS":
            tok.next("CHANNELS")
            channels.append(_parse_channels(tok, name))
        else:
            channels.append(())
        while True:
            line = tok.current_line
            kw = tok.next(f"the body of joint {name!r} (missing '}}'?)")
            if kw == "}":
                return
            if kw == "JOINT":
                joint(j)
            elif kw == "End":
                line = tok.current_line
                site = tok.next("'Site'")
                if site != "Site":
                    raise DatasetError(f"{source}: line {line}: expected 'End Site', found 'End {site}'")
                tok.expect("{", f"opening the End Site of joint {name!r}")
                end_sites.append((j, _parse_offset(tok, f"the End Site of joint {name!r}")))
                tok.expect("}", f"closing the End Site of joint {name!r}")
            else:
                raise DatasetError(
                    f"{source}: line {line}: unexpected {kw!r} in joint {name!r} (expected JOINT, End Site or '}}')"
                )

    joint(-1)

    # MOTION
    line = tok.current_line
    kw = tok.peek()
    if kw is None:
        raise DatasetError(f"{source}: MOTION section is missing (the file ends after the HIERARCHY section)")
    if kw == "ROOT":
        raise DatasetError(f"{source}: line {line}: a second ROOT is not supported")
    if kw != "MOTION":
        raise DatasetError(f"{source}: line {line}: expected 'MOTION' after the HIERARCHY section, found {kw!r}")
    tok.next("MOTION")
    if tok.rest_of_line():
        raise DatasetError(f"{source}: line {line}: unexpected text after 'MOTION'")
    i = tok.line_no  # 0-based index of the first line after MOTION

    def header(label: str, i: int) -> tuple[str, int]:
        while i < len(lines) and not lines[i].strip():
            i += 1
        if i >= len(lines):
            raise DatasetError(f"{source}: file is truncated: '{label}' line missing after MOTION")
        ln = lines[i].strip()
        if not ln.startswith(label):
            raise DatasetError(f"{source}: line {i + 1}: expected '{label} <value>', found {ln[:40]!r}")
        return ln[len(label) :].strip(), i + 1

    value, i = header("Frames:", i)
    try:
        n_frames = int(value)
        if n_frames < 0:
            raise ValueError
    except ValueError:
        raise DatasetError(
            f"{source}: line {i}: field 'Frames' must be a non-negative integer, got {value!r}"
        ) from None
    value, i = header("Frame Time:", i)
    try:
        frame_time = float(value)
    except ValueError:
        raise DatasetError(f"{source}: line {i}: field 'Frame Time' must be a number, got {value!r}") from None
    if not (math.isfinite(frame_time) and frame_time > 0):
        raise DatasetError(f"{source}: line {i}: field 'Frame Time' must be positive, got {value!r}")

    n_chan = sum(len(c) for c in channels)
    body = [(k + 1, ln) for k, ln in enumerate(lines[i:], start=i) if ln.strip()]
    if len(body) != n_frames:
        hint = " (file truncated?)" if len(body) < n_frames else ""
        raise DatasetError(
            f"{source}: field 'Frames' declares {n_frames} frames but the MOTION section has "
            f"{len(body)} lines of values{hint}"
        )
    frames = np.empty((n_frames, n_chan))
    for f, (line_no, ln) in enumerate(body):
        vals = ln.split()
        if len(vals) != n_chan:
            hint = " (file truncated?)" if f == n_frames - 1 and len(vals) < n_chan else ""
            raise DatasetError(
                f"{source}: line {line_no} (frame {f}): {len(vals)} values, but the hierarchy "
                f"declares {n_chan} channels{hint}"
            )
        try:
            frames[f] = np.array(vals, dtype=np.float64)
        except ValueError:
            for col, v in enumerate(vals):
                try:
                    float(v)
                except ValueError:
                    raise DatasetError(
                        f"{source}: line {line_no} (frame {f}), column {col + 1} "
                        f"(channel {_channel_label(names, channels, col)}): {v!r} is not a number"
                    ) from None
            raise  # pragma: no cover
        bad = ~np.isfinite(frames[f])
        if bad.any():
            col = int(np.argmax(bad))
            raise DatasetError(
                f"{source}: line {line_no} (frame {f}), column {col + 1} "
                f"(channel {_channel_label(names, channels, col)}): {vals[col]!r} is not finite"
            )
    return BVH(
        names=names,
        parents=parents,
        offsets=np.array(offsets).reshape(-1, 3),
        channels=channels,
        frame_time=frame_time,
        frames=frames,
        end_sites=end_sites,
        source=source,
    )


def _channel_label(names, channels, col: int) -> str:
    for name, ch in zip(names, channels):
        if col < len(ch):
            return f"{name}.{ch[col]}"
        col -= len(ch)
    return "?"  # pragma: no cover


def read_bvh(path: str | Path) -> BVH:
    """Read and parse a BVH file (see `parse_bvh`)."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: BVH file does not exist")
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read file ({exc.strerror})") from None
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        text = data.decode("latin-1")
    return parse_bvh(text, str(path))


__all__ = [
    "BVH",
    "read_bvh",
    "parse_bvh",
    "euler_to_matrix",
    "axis_rotation",
    "forward_kinematics",
    "ROTATION_CHANNELS",
    "POSITION_CHANNELS",
    "CHANNEL_NAMES",
]
