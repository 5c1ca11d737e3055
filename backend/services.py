"""What the server holds while it runs: database, event bus, instrument, runner, merge jobs."""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass, field
from typing import Any
from urllib.parse import parse_qs, urlsplit

from sqlalchemy import Engine
from sqlalchemy.exc import DatabaseError
from sqlalchemy.orm import Session, sessionmaker

from backend.acquisition.planner import InstrumentLimits
from backend.acquisition.runner import Runner
from backend.auth import load_or_create_token
from backend.db.models import MergeJob, Run, SemImageRecord, SemRegistrationRecord
from backend.db.patch_store import read_merge_detail, read_patch
from backend.db.session import make_engine, migrate, session_factory
from backend.events import EventBus
from backend.live_merge import LiveMergeService
from backend.merge_jobs import MergeService
from backend.security.authority import Authority
from backend.security.lock import OperatorLock
from backend.sem_files import sem_view
from backend.settings import Settings
from backend.status_cache import StatusCache
from backend.viewer import MERGED_BUDGET, HeightMap, Viewer
from backend.viewer_access import admission
from hardware.microscope import Microscope, open_microscope
from merge.correlative import Similarity
from merge.io.detail import detail_frame
from merge.io.overlay import sem_on_mosaic

log = logging.getLogger("mosaic_afm.server")


class DatabaseDamaged(RuntimeError):
    """The database cannot be read; the message names the file and the ways back."""

    def __init__(self, settings: Settings, problem: str) -> None:
        url = settings.database
        path = url.removeprefix("sqlite:///") if url.startswith("sqlite:///") else url
        super().__init__(
            f"the database {path} is damaged ({problem}). Stop every server on it and keep a "
            f"copy of it (with {path}-wal and {path}-shm beside it, which may hold the last "
            f"changes). Then recover what it holds: sqlite3 {path} .recover | sqlite3 "
            f"recovered.sqlite, and put recovered.sqlite in its place; or restore a copy made "
            f"by mosaic-afm backup. The run files under {settings.runs_dir} are not touched."
        )


def instrument_url(settings: Settings) -> str:
    """The instrument string, with the simulated clock speed from the settings."""
    url = settings.instrument
    if url.startswith("sim://") and "speed" not in parse_qs(urlsplit(url).query):
        url += ("&" if "?" in url else "?") + f"speed={settings.sim_speed}"
    return url


@dataclass
class Services:
    settings: Settings
    engine: Engine
    sessions: sessionmaker[Session]
    events: EventBus
    microscope: Microscope
    runner: Runner
    merges: MergeService
    token: str
    token_created: bool
    authority: Authority
    lock: OperatorLock
    viewer: Viewer | None = None
    token_announced: bool = False
    status: StatusCache = field(default_factory=StatusCache)

    @property
    def limits(self) -> InstrumentLimits:
        m = self.microscope
        scanner = m.scanner
        fine = scanner.fine_range if scanner is not None else None
        return InstrumentLimits(
            fine_range=fine or (m.robot_x.fine_range, m.robot_y.fine_range),
            scan=m.scan_envelope(),
        )

    @classmethod
    def open(cls, settings: Settings) -> Services:
        """Migrate the database, open the instrument, recover from a previous stop;
        :class:`DatabaseDamaged` when the database cannot be read."""
        settings.runs_dir.mkdir(parents=True, exist_ok=True)
        try:
            migrate(settings.database)
            engine = make_engine(settings.database)
            with engine.connect() as connection:
                check = connection.exec_driver_sql("PRAGMA quick_check").scalar()
            if check not in (None, "ok"):
                raise DatabaseDamaged(settings, f"quick_check says {check!r}")
        except DatabaseError as exc:
            raise DatabaseDamaged(settings, str(exc.orig or exc)) from None
        sessions = session_factory(engine, data_dir=settings.data_dir)
        events = EventBus(sessions)
        token, created = load_or_create_token(settings)
        authority = Authority(settings, sessions, token)
        authority.check_ready()
        microscope = open_microscope(instrument_url(settings))
        merges = MergeService(sessions, events, data_dir=settings.data_dir)
        runner = Runner(
            microscope,
            sessions,
            events,
            data_dir=settings.data_dir,
            reserve=settings.disk_reserve,
        )
        if settings.live_merge:
            runner.live = LiveMergeService(events, on_verdict=runner.tell_verdict)
        if settings.auto_merge:
            runner.on_completed = lambda run_id: _auto_merge(merges, run_id)
        viewer = None
        if settings.viewer:
            viewer = Viewer(
                host=settings.host,
                port=settings.viewer_port,
                admit=admission(token=token, api_port=settings.port, origins=settings.cors_origins),
            )
            events.listen(ViewerFeed(viewer, sessions, runner.live))
        status = StatusCache()
        events.listen(status)
        runner.recover()
        runner.start_supervisor()
        merges.recover()
        merges.start()
        return cls(
            settings,
            engine,
            sessions,
            events,
            microscope,
            runner,
            merges,
            token,
            created,
            authority,
            OperatorLock(sessions),
            viewer,
            status=status,
        )

    def close(self) -> None:
        self.runner.close()
        if self.runner.live is not None:
            self.runner.live.close()
        self.merges.close()
        self.events.close()
        if self.viewer is not None:
            self.viewer.close()
        self.microscope.close()
        self.engine.dispose()


class ViewerFeed:
    """Event listener: stored patches, the live mosaic and finished merges go to the 3D
    viewer."""

    def __init__(
        self, viewer: Viewer, sessions: sessionmaker[Session], live: LiveMergeService | None = None
    ) -> None:
        self.viewer = viewer
        self.sessions = sessions
        self.live = live
        #: runs whose live mosaic waits in the viewer's queue: one update in flight at most
        self._live_queued: set[int] = set()
        self._lock = threading.Lock()

    def __call__(self, event: dict[str, Any]) -> None:
        data = event.get("data") or {}
        if event["kind"] == "progress" and "patch" in data:
            run_id, index, total = event["run_id"], int(data["patch"]), int(data["total"])
            self.viewer.submit(lambda: self._patch(run_id, index, total))
        elif event["kind"] == "merge" and data.get("state") == "done":
            job_id = int(data["job"])
            self.viewer.submit(lambda: self._mosaic(job_id))
        elif event["kind"] == "sem" and data.get("accepted") and "registration" in data:
            registration = int(data["registration"])
            self.viewer.submit(lambda: self._drape(registration))
        elif event["kind"] == "live" and "patches_merged" in data and event.get("run_id"):
            run_id = int(event["run_id"])
            with self._lock:  # the viewer draws the newest; updates that come meanwhile wait
                if run_id in self._live_queued:
                    return
                self._live_queued.add(run_id)
            self.viewer.submit(lambda: self._live(run_id))

    def _live(self, run_id: int) -> None:
        with self._lock:
            self._live_queued.discard(run_id)
        held = self.live.mosaic(run_id) if self.live is not None else None
        if held is None:
            return
        heights, document = held
        origin = (float(document["origin"][0]), float(document["origin"][1]))
        pixel = (float(document["pixel_size"][0]), float(document["pixel_size"][1]))
        self.viewer.show_live(run_id, HeightMap(heights, origin, pixel))

    def _patch(self, run_id: int, index: int, total: int) -> None:
        with self.sessions() as session:
            run = session.get(Run, run_id)
            if run is None:
                return
            path = run.file
        stored = read_patch(path, index)
        self.viewer.show_patch(
            run_id,
            index,
            HeightMap(stored.heights, stored.origin, stored.pixel_size),
            patches=total,
        )

    def _mosaic(self, job_id: int) -> None:
        with self.sessions() as session:
            job = session.get(MergeJob, job_id)
            run = session.get(Run, job.run_id) if job is not None else None
            if job is None or run is None or not job.result_group:
                return
            path, group = run.file, job.result_group
        heights, k, document = read_merge_detail(path, group, MERGED_BUDGET)
        origin, pixel = detail_frame(
            (float(document["origin"][0]), float(document["origin"][1])),
            (float(document["pixel_size"][0]), float(document["pixel_size"][1])),
            k,
        )
        self.viewer.show_mosaic(job_id, HeightMap(heights, origin, pixel))

    def _drape(self, registration_id: int) -> None:
        """The SEM image a merged mosaic was registered on, draped over it in the viewer."""
        with self.sessions() as session:
            record = session.get(SemRegistrationRecord, registration_id)
            job = session.get(MergeJob, record.merge_id) if record is not None else None
            run = session.get(Run, job.run_id) if job is not None else None
            sem = session.get(SemImageRecord, record.sem_id) if record is not None else None
            if record is None or job is None or run is None or sem is None:
                return
            if not job.result_group:
                return
            path, group = run.file, job.result_group
            view = sem_view(sem)
            t = Similarity(*record.transform)
        heights, k, document = read_merge_detail(path, group, MERGED_BUDGET)
        origin, pixel = detail_frame(
            (float(document["origin"][0]), float(document["origin"][1])),
            (float(document["pixel_size"][0]), float(document["pixel_size"][1])),
            k,
        )
        signal = sem_on_mosaic(view, heights.shape, origin=origin, pixel_size=pixel, transform=t)
        self.viewer.drape(record.merge_id, HeightMap(heights, origin, pixel), signal)


def _auto_merge(merges: MergeService, run_id: int) -> None:
    """The completed run's merge: every stored patch but those the quality gate flagged (when
    re-scans are on: with them off, nothing is left out)."""
    with merges.sessions() as session:
        run = session.get(Run, run_id)
        flagged = (
            {p.index for p in run.patches if p.quality == "flagged"}
            if run is not None and run.rescan_enabled
            else set()
        )
        stored = [p.index for p in run.patches if p.step == "stored"] if run is not None else []
    chosen = [i for i in stored if i not in flagged] if flagged else None
    merges.submit(run_id, method="default", parameters={}, patches=chosen)
