from __future__ import annotations

from pathlib import Path

import pytest
from sqlalchemy import inspect, select

from backend.db.models import Base, Run
from backend.db.session import make_engine, migrate, session_factory


def test_upgrade_an_empty_database_to_head(tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path / 'db' / 'm.sqlite'}"
    migrate(url)
    engine = make_engine(url)
    tables = set(inspect(engine).get_table_names())
    assert {"runs", "patches", "merge_jobs", "events", "sem_images", "calibrations"} <= tables
    assert "alembic_version" in tables
    # the migrated schema is exactly what the models declare
    for table in Base.metadata.sorted_tables:
        cols = {c["name"] for c in inspect(engine).get_columns(table.name)}
        assert cols == {c.name for c in table.columns}
    with engine.connect() as conn:
        assert conn.exec_driver_sql("PRAGMA journal_mode").scalar() == "wal"


def test_downgrade_and_upgrade_again_keeps_working(tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path / 'm.sqlite'}"
    migrate(url)
    migrate(url)  # idempotent at head
    from alembic import command
    from alembic.config import Config

    from backend.db.session import ALEMBIC_DIR

    cfg = Config()
    cfg.set_main_option("script_location", str(ALEMBIC_DIR))
    cfg.set_main_option("sqlalchemy.url", url)
    cfg.attributes["configure_logger"] = False
    command.downgrade(cfg, "base")
    assert "runs" not in inspect(make_engine(url)).get_table_names()
    migrate(url)
    engine = make_engine(url)
    with session_factory(engine)() as session:
        assert session.scalars(select(Run)).all() == []


def test_foreign_keys_are_enforced(tmp_path: Path) -> None:
    from sqlalchemy.exc import IntegrityError

    from backend.db.models import PatchRecord

    url = f"sqlite:///{tmp_path / 'm.sqlite'}"
    migrate(url)
    with session_factory(make_engine(url))() as session:
        session.add(PatchRecord(run_id=999, index=0, row=0, col=0, origin_x=0, origin_y=0))
        with pytest.raises(IntegrityError):
            session.commit()
