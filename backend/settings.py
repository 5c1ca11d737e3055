"""One fail-fast settings class, from the environment (``MOSAIC_*``) or a ``.env`` file."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field, SecretStr, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict


class Settings(BaseSettings):
    """Server settings. Every value is checked when the server starts, not when first used."""

    model_config = SettingsConfigDict(env_prefix="MOSAIC_", env_file=".env", extra="ignore")

    data_dir: Path = Field(default=Path("data"), description="patch files, database, token")
    database_url: str | None = Field(default=None, description="default: SQLite in data_dir")
    instrument: str = Field(default="sim://", description="sim://... or mcs://stage=..;robot=..")
    sim_speed: str = Field(default="max", description="simulated s per wall s, or 'max'")
    api_token: SecretStr | None = Field(default=None, description="bearer token for changes")
    host: str = "127.0.0.1"
    port: int = Field(default=8000, ge=1, le=65535)
    viewer_port: int = Field(default=8080, ge=1, le=65535)
    viewer: bool = Field(default=True, description="serve the viser 3D viewer")
    auto_merge: bool = True
    live_merge: bool = Field(
        default=True,
        description="merge every stored patch live and re-scan those the quality gate fails",
    )
    cors_origins: list[str] = Field(
        default_factory=list, description="origins allowed cross-site (none: CORS closed)"
    )
    max_upload_bytes: int = Field(
        default=256 * 1024 * 1024, gt=0, description="largest upload (files), bytes"
    )
    max_json_bytes: int = Field(
        default=1024 * 1024, gt=0, description="largest body of any other request, bytes"
    )
    hosts: list[str] | None = Field(
        default=None,
        description="Host names the server answers for (default: its own, and the loopback "
        "names when it listens on loopback; any when it listens on every interface)",
    )
    disk_reserve: int = Field(
        default=50 * 1024 * 1024,
        ge=0,
        description="bytes kept free in data_dir: a run does not start, nor scan its next "
        "patch, when a patch would leave less",
    )

    auth: Literal["single", "users"] = Field(
        default="single",
        description="single: one secret token, reads open (a one-person bench); users: "
        "logins, roles, keys and the operator lock, every request with an identity",
    )
    anonymous_read: bool = Field(
        default=False, description="users mode: let requests without an identity read"
    )
    access_ttl: int = Field(
        default=900, ge=30, le=86400, description="life of an access token (users mode), s"
    )
    refresh_ttl: int = Field(
        default=7 * 86400, ge=300, description="life of a login session without use, s"
    )
    login_attempts: int = Field(
        default=5, ge=1, description="failed logins of a name or an address before a pause"
    )
    pam_service: str = Field(default="login", description="the PAM service users log in by")
    pam_confdir: Path | None = Field(
        default=None, description="a PAM configuration directory instead of /etc/pam.d"
    )
    secure_cookies: bool = Field(
        default=False, description="mark the session cookies Secure (the server behind HTTPS)"
    )

    @field_validator("api_token")
    @classmethod
    def _token(cls, value: SecretStr | None) -> SecretStr | None:
        if value is None or not value.get_secret_value().strip():
            return None  # unset or empty: one is generated into the data dir
        if len(value.get_secret_value()) < 16:
            raise ValueError("api_token must be at least 16 characters (or unset to generate one)")
        return value

    @field_validator("sim_speed")
    @classmethod
    def _speed(cls, value: str) -> str:
        if value == "max":
            return value
        try:
            speed = float(value)
        except ValueError:
            raise ValueError("sim_speed must be 'max' or a positive number") from None
        if not speed > 0:
            raise ValueError("sim_speed must be 'max' or a positive number")
        return value

    @property
    def speed(self) -> float | None:
        """Simulated seconds per wall second; None for as fast as possible."""
        return None if self.sim_speed == "max" else float(self.sim_speed)

    @property
    def database(self) -> str:
        """The SQLAlchemy URL of the database."""
        return self.database_url or f"sqlite:///{(self.data_dir / 'mosaic.sqlite').as_posix()}"

    @property
    def runs_dir(self) -> Path:
        """Where the HDF5 files of the runs live."""
        return self.data_dir / "runs"
