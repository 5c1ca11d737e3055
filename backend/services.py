"""What the server holds while it runs: database, event bus, instrument, runner, merge jobs."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from urllib.parse import parse_qs, urlsplit

from sqlalchemy import Engine
from sqlalchemy.orm import Session, sessionmaker

from backend.acquisition.planner import InstrumentLimits
from backend.acquisition.runner import Runner
from backend.auth import load_or_create_token
from backend.db.session import make_engine, migrate, session_factory
from backend.events import EventBus
from backend.merge_jobs import MergeService
from backend.settings import Settings
from hardware.microscope import Microscope, open_microscope

log = logging.getLogger("mosaic_afm.server")


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
    token_announced: bool = False

    @property
    def limits(self) -> InstrumentLimits:
        m = self.microscope
        return InstrumentLimits(fine_range=(m.robot_x.fine_range, m.robot_y.fine_range))

    @classmethod
    def open(cls, settings: Settings) -> Services:
        """Migrate the database, open the instrument, recover from a previous stop."""
        settings.runs_dir.mkdir(parents=True, exist_ok=True)
        migrate(settings.database)
        engine = make_engine(settings.database)
        sessions = session_factory(engine)
        events = EventBus(sessions)
        token, created = load_or_create_token(settings)
        microscope = open_microscope(instrument_url(settings))
        merges = MergeService(sessions, events)
        runner = Runner(microscope, sessions, events)
        if settings.auto_merge:
            runner.on_completed = lambda run_id: _auto_merge(merges, run_id)
        runner.recover()
        merges.recover()
        merges.start()
        return cls(settings, engine, sessions, events, microscope, runner, merges, token, created)

    def close(self) -> None:
        self.runner.close()
        self.merges.close()
        self.events.close()
        self.microscope.close()
        self.engine.dispose()


def _auto_merge(merges: MergeService, run_id: int) -> None:
    merges.submit(run_id, method="default", parameters={}, patches=None)
