"""map/: the run's saved map (map.json, map.bin; docs/MAPS.md), which ``ti-fusion slam --map``, ``mesh`` and
``inspect`` read, or the folder ``--save-map DIR`` names. Like map.ply, written when the run ends, and not
after a stop (Ctrl-C, SIGTERM); not at all with ``--no-save-map``."""

from __future__ import annotations

from pathlib import Path

from ti_fusion.sinks.base import Run, Sink


class SavedMapSink(Sink):
    name = "saved_map"
    commands = ("slam",)
    off_flag = "--no-save-map"
    help = "do not write the run's saved map (map/ in the run folder, or --save-map DIR; docs/MAPS.md)"

    @classmethod
    def wanted(cls, command, config, outputs) -> bool:
        """Not after --localize: that session changes no map, and the map it tracked against stays as it was."""
        return super().wanted(command, config, outputs) and not config.map.localize

    def start(self, run: Run) -> None:
        """A --save-map folder that holds something other than a saved map is refused before the first frame."""
        from ti_fusion.errors import OutputError
        from ti_fusion.io.map_files import DATA, HEADER

        folder = run.config.map.save_map
        if not folder:
            return
        path = Path(folder)
        if path.exists() and not path.is_dir():
            raise OutputError(path, "--save-map: is a file, not a folder")
        others = sorted(n for n in (path.iterdir() if path.is_dir() else ()) if n.name not in (HEADER, DATA))
        if others:
            raise OutputError(path, f"--save-map: holds {others[0].name}{' and more' if len(others) > 1 else ''}, "
                                    "not a saved map: give a new folder or one holding only a saved map")

    def finish(self, run: Run) -> dict:
        from ti_fusion.io.map_files import DATA, HEADER

        slam = run.step.slam
        target = Path(run.config.map.save_map) if run.config.map.save_map else run.out.file("map")
        state, surfels = slam.map_state(), slam.surfels  # read here; written on an outputs' thread
        keyframes = 0 if slam.loop is None else len(slam.loop.keyframes)

        def write() -> dict:
            folder = state.write(target)
            return {"saved_map": {"folder": str(folder), "surfels": surfels, "keyframes": keyframes,
                                  "bytes": sum((folder / name).stat().st_size for name in (HEADER, DATA))}}

        run.in_background(write)
        return {}
