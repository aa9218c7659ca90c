"""The 3D view (PyVista in Qt): the scene, the store's octree leaves, its reference cameras as
pickable frusta, the client's path, camera and prefetch frustum.

A left click (press and release at one spot) picks the nearest reference frustum under the
cursor (a VTK cell picker restricted to the frusta) and emits :attr:`SceneView.record_picked`.
The click's position is the render window interactor's event position (VTK display
coordinates, origin bottom-left, device pixels): the observers sit on the interactor, but VTK
hands them the interactor style as the caller, which has no event position.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pyvista as pv
from PySide6 import QtCore, QtWidgets
from pyvistaqt import QtInteractor

from icbtool_gui.model import Leaf, frustum_points

#: Colours (RGB 0-1).
COLOURS = {
    "record": (0.35, 0.65, 1.0),
    "picked": (1.0, 0.2, 1.0),
    "used": (1.0, 0.95, 0.2),
    "client": (0.1, 0.9, 0.2),
    "prefetch": (1.0, 0.55, 0.0),
    "path": (0.7, 0.7, 0.7),
}

#: The 12 edges of a box whose 8 corners are ordered x fastest, then y, then z.
_BOX_EDGES = [(0, 1), (1, 3), (3, 2), (2, 0), (4, 5), (5, 7), (7, 6), (6, 4)]
_BOX_EDGES += [(0, 4), (1, 5), (2, 6), (3, 7)]


def pyramid(points: np.ndarray) -> pv.PolyData:
    """A closed pyramid from :func:`icbtool_gui.model.frustum_points` (apex + 4 base corners)."""
    faces = np.array([3, 0, 1, 2, 3, 0, 2, 3, 3, 0, 3, 4, 3, 0, 4, 1, 4, 1, 2, 3, 4])
    return pv.PolyData(np.asarray(points, np.float64), faces)


def frustum_lines(points: np.ndarray) -> pv.PolyData:
    """The 8 edges of a frustum pyramid as lines."""
    edges = [(0, 1), (0, 2), (0, 3), (0, 4), (1, 2), (2, 3), (3, 4), (4, 1)]
    lines = np.array([[2, a, b] for a, b in edges]).ravel()
    return pv.PolyData(np.asarray(points, np.float64), lines=lines)


def leaf_boxes(leaves: list[Leaf]) -> pv.PolyData:
    """Wireframe boxes of the leaves, with cell data ``records`` and ``hits`` per edge."""
    pts, lines, rec, hits = [], [], [], []
    for n, leaf in enumerate(leaves):
        lo, hi = leaf.bounds
        corners = np.array(
            [[x, y, z] for z in (lo[2], hi[2]) for y in (lo[1], hi[1]) for x in (lo[0], hi[0])]
        )
        pts.append(corners)
        lines += [[2, 8 * n + a, 8 * n + b] for a, b in _BOX_EDGES]
        rec += [leaf.records] * len(_BOX_EDGES)
        hits += [leaf.hits] * len(_BOX_EDGES)
    poly = pv.PolyData(np.concatenate(pts), lines=np.array(lines).ravel())
    poly.cell_data["records"] = np.array(rec, np.float64)
    poly.cell_data["hits"] = np.array(hits, np.float64)
    return poly


def scene_mesh(scene: Any) -> pv.PolyData:
    """The scene's triangles with each face coloured by its material's albedo (emitters
    white), as cell data ``rgb`` (uint8)."""
    faces = np.hstack([np.full((len(scene.faces), 1), 3), scene.faces]).ravel()
    mesh = pv.PolyData(np.asarray(scene.vertices, np.float64), faces)
    albedo = np.array([np.asarray(m.albedo, np.float64)[:3] for m in scene.materials])
    emit = np.array([np.max(np.asarray(m.emission, np.float64)) > 0 for m in scene.materials])
    albedo[emit] = 1.0
    colour = albedo[np.asarray(scene.face_material, np.int64)]
    mesh.cell_data["rgb"] = np.clip(255 * colour, 0, 255).astype(np.uint8)
    return mesh


class SceneView(QtCore.QObject):
    """The 3D view. :attr:`widget` is the Qt widget to place in a layout.

    Signals:
        record_picked(int): a reference frustum was clicked (its record id).
    """

    record_picked = QtCore.Signal(int)

    def __init__(self, parent: QtWidgets.QWidget | None = None) -> None:
        super().__init__(parent)
        self.plotter = QtInteractor(parent, auto_update=False)
        self.widget: QtWidgets.QWidget = self.plotter
        self.plotter.set_background("#1e1e24")
        self.record_actors: dict[int, Any] = {}  # record id -> actor
        self._actor_ids: dict[int, int] = {}  # id(vtk actor) -> record id
        self.client_points: np.ndarray | None = None
        self.prefetch_points: np.ndarray | None = None
        self.leaf_count = 0
        self._picked: int | None = None
        self._used: int | None = None
        self._press: tuple[int, int] | None = None
        import vtk

        self._picker = vtk.vtkCellPicker()
        self._picker.SetTolerance(0.002)
        self._picker.PickFromListOn()
        iren = self.plotter.iren
        iren.add_observer("LeftButtonPressEvent", self._on_press)
        iren.add_observer("LeftButtonReleaseEvent", self._on_release)

    # -------------------------------------------------------------- content
    def set_scene(self, scene: Any, frustum_depth: float) -> None:
        """The scene's mesh (back faces culled: a room's walls, whose normals point inwards, hide
        only when they face away, so the room shows its inside) and a view from outside."""
        p = self.plotter
        p.add_mesh(
            scene_mesh(scene), scalars="rgb", rgb=True, culling="back", name="scene",
            pickable=False, show_scalar_bar=False,
        )  # fmt: skip
        b = np.asarray(scene.bounds, np.float64)
        centre, diag = b.mean(0), float(np.linalg.norm(b[1] - b[0]))
        up = np.asarray(scene.up, np.float64)
        cam = scene.default_camera
        fwd = np.asarray(cam.forward if cam is not None else (0, 0, -1), np.float64)
        side = np.cross(fwd, up)
        eye = centre - 1.2 * diag * fwd + 0.5 * diag * up + 0.35 * diag * side
        p.camera_position = [tuple(eye), tuple(centre), tuple(up)]
        p.reset_camera(bounds=b.T.ravel())
        self._depth = frustum_depth

    def set_path(self, cameras: list[Any]) -> None:
        """The client's path as a polyline through its camera centres."""
        pts = np.array([c.position for c in cameras], np.float64)
        if len(pts) >= 2:
            self.plotter.add_mesh(
                pv.lines_from_points(pts), color=COLOURS["path"], line_width=2, name="path",
                pickable=False,
            )  # fmt: skip

    def set_records(
        self,
        records: list[Any],
        leaves: list[Leaf],
        render: bool = True,
        colour_by: str = "records",
    ) -> None:
        """One pickable frustum actor per record (only new records get a new actor, evicted
        ones lose theirs), and the octree leaves coloured by ``colour_by`` ("records" or
        "hits")."""
        p = self.plotter
        keep = {r.record_id for r in records}
        for rid in [r for r in self.record_actors if r not in keep]:
            actor = self.record_actors.pop(rid)
            self._actor_ids.pop(id(actor), None)
            self._picker.DeletePickList(actor)
            p.remove_actor(actor, render=False)
        for r in records:
            if r.record_id in self.record_actors:
                continue
            actor = p.add_mesh(
                pyramid(frustum_points(r.camera, self._depth)), color=COLOURS["record"],
                opacity=0.35, show_edges=True, edge_color=COLOURS["record"], pickable=True,
                name=f"record-{r.record_id}", reset_camera=False, render=False,
            )  # fmt: skip
            self.record_actors[r.record_id] = actor
            self._actor_ids[id(actor)] = r.record_id
            self._picker.AddPickList(actor)
        self.leaf_count = len(leaves)
        if leaves:
            boxes = leaf_boxes(leaves)
            hi = max(1.0, float(boxes.cell_data[colour_by].max()))
            p.remove_actor("leaves", render=False)  # its scalar bar title may change
            p.add_mesh(
                boxes, scalars=colour_by, cmap="plasma", clim=(0, hi), line_width=1.5,
                name="leaves", pickable=False, reset_camera=False, render=False,
                scalar_bar_args={"title": f"{colour_by} per leaf", "n_labels": 3, "fmt": "%.0f",
                                 "position_x": 0.70, "position_y": 0.86, "width": 0.27,
                                 "height": 0.09, "title_font_size": 12,
                                 "label_font_size": 10},
            )  # fmt: skip
        else:
            p.remove_actor("leaves", render=False)
        self._recolour()
        if render:
            self.render()

    def set_client(self, camera: Any, prefetch: Any, render: bool = True) -> None:
        """The client's frustum (green) and its prefetch frustum (orange, 1.5x as long)."""
        self.client_points = frustum_points(camera, self._depth)
        self.prefetch_points = frustum_points(prefetch, 1.5 * self._depth)
        p = self.plotter
        p.add_mesh(
            frustum_lines(self.client_points), color=COLOURS["client"], line_width=3,
            name="client", pickable=False, reset_camera=False, render=False,
        )  # fmt: skip
        p.add_mesh(
            frustum_lines(self.prefetch_points), color=COLOURS["prefetch"], line_width=2,
            name="prefetch", pickable=False, reset_camera=False, render=False,
        )  # fmt: skip
        if render:
            self.render()

    def set_used(self, record_id: int | None, render: bool = True) -> None:
        """Highlight the record that answered the current frame (yellow)."""
        self._used = record_id
        self._recolour()
        if render:
            self.render()

    @property
    def used_record(self) -> int | None:
        """The record that answered the current frame (None: rendered anew or generated)."""
        return self._used

    def set_picked(self, record_id: int | None) -> None:
        self._picked = record_id
        self._recolour()
        self.render()

    def _recolour(self) -> None:
        for rid, actor in self.record_actors.items():
            c = COLOURS["record"]
            if rid == self._used:
                c = COLOURS["used"]
            if rid == self._picked:
                c = COLOURS["picked"]
            actor.prop.color = c
            actor.prop.edge_color = c

    def frame_all(self) -> None:
        """Fit everything shown (scene, path, frusta) in the view, keeping its direction."""
        self.plotter.reset_camera()

    def frame_all_and_render(self) -> None:
        self.frame_all()
        self.render()

    def render(self) -> None:
        self.plotter.render()

    # -------------------------------------------------------------- picking
    def display_xy(self, point: np.ndarray) -> tuple[int, int]:
        """VTK display coordinates (origin bottom-left, device pixels) of world ``point`` (3,)."""
        ren = self.plotter.renderer
        ren.SetWorldPoint(*np.asarray(point, np.float64), 1.0)
        ren.WorldToDisplay()
        x, y, _ = ren.GetDisplayPoint()
        return int(round(x)), int(round(y))

    def widget_xy(self, point: np.ndarray) -> tuple[int, int]:
        """Qt widget coordinates (origin top-left, logical pixels) of world ``point`` (3,):
        where a mouse click on :attr:`widget` lands on it."""
        x, y = self.display_xy(point)
        ratio = self.widget.devicePixelRatioF()  # QVTKRenderWindowInteractor's inverse mapping
        return int(round(x / ratio)), int(round(self.widget.height() - 1 - y / ratio))

    def pick_at(self, x: int, y: int) -> int | None:
        """The record whose frustum is nearest under display point (x, y), or None; emits
        :attr:`record_picked` when there is one."""
        if not self.record_actors:
            return None
        if not self._picker.Pick(x, y, 0, self.plotter.renderer):
            return None
        rid = self._actor_ids.get(id(self._picker.GetActor()))
        if rid is None:  # pyvista may hand out a new wrapper of the same vtkActor
            rid = next(
                (r for r, a in self.record_actors.items() if a == self._picker.GetActor()), None
            )
        if rid is not None:
            self.record_picked.emit(rid)
        return rid

    def _event_position(self) -> tuple[int, int]:
        x, y = self.plotter.iren.interactor.GetEventPosition()
        return int(x), int(y)

    def _on_press(self, _obj: Any, _event: str) -> None:
        self._press = self._event_position()

    def _on_release(self, _obj: Any, _event: str) -> None:
        pos = self._event_position()
        press, self._press = self._press, None
        if press is not None and max(abs(pos[0] - press[0]), abs(pos[1] - press[1])) <= 3:
            self.pick_at(*pos)

    def close(self) -> None:
        self.plotter.close()


__all__ = ["COLOURS", "SceneView", "frustum_lines", "leaf_boxes", "pyramid", "scene_mesh"]
