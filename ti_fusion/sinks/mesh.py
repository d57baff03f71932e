"""``slam --mesh``: a coloured triangle mesh of the map (docs/MESH.md): with mesh.method = "depth" each tracked
frame's depth integrated at its pose as the run goes; at the end the mesh on the log's /map/mesh, then
mesh.ply and mesh.glb."""

from __future__ import annotations

from ti_fusion.config import Config
from ti_fusion.sinks.base import Run, Sink


class MeshSink(Sink):
    name = "mesh"
    commands = ("slam",)

    @classmethod
    def wanted(cls, command: str, config: Config, outputs: dict[str, bool]) -> bool:
        return command in cls.commands and outputs.get(cls.name, config.mesh.after_run)  # --mesh sets after_run

    def start(self, run: Run) -> None:
        from ti_fusion.mapping.mesh import RunMesh  # Taichi kernels and scikit-image: only with --mesh

        self.mesh = RunMesh(run.config.mesh)

    def frame(self, run: Run, frame, result) -> None:
        if result.tracked:
            self.mesh.integrate(frame, result.pose)

    def finish(self, run: Run) -> dict:
        if run.step.mapper.count:
            self.mesh.make(run.step.mapper, run.log, run.results[-1].timestamp)
        return self.mesh.outputs(run.out)
