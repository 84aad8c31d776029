"""The local stack's settings (`sim2act up`): ports, and the nightly deployment's schedule. The
campaign the deployments run by default is a CampaignConfig, given as `sim2act run` takes it.

One model, validated before any process starts: a bad port or cron line costs one line.
"""

from __future__ import annotations

from zoneinfo import available_timezones

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

# Loopback only: the stack has no authentication; reaching it from elsewhere is a deliberate
# choice made with a reverse proxy (docs/service.md), not a flag.
HOST = "127.0.0.1"
SERVICES = ("prefect", "mlflow", "dashboard", "deployments")


class ServiceConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    prefect_port: int = Field(default=4200, ge=1024, le=65535)
    mlflow_port: int = Field(default=5000, ge=1024, le=65535)
    dashboard_port: int = Field(default=8765, ge=1024, le=65535)
    nightly_cron: str = Field(default="0 2 * * *", description="when the nightly iteration starts (cron, 5 fields)")
    timezone: str = Field(default="UTC", description="IANA name, e.g. Europe/Berlin")

    @field_validator("nightly_cron")
    @classmethod
    def _cron(cls, value: str) -> str:
        from prefect.client.schemas.schedules import CronSchedule  # Prefect's own rules, so the server agrees

        # 5 fields as --help shows (Prefect would also take a seconds field and @daily)
        refusal = ValueError(f"expected a 5-field cron line (e.g. '0 2 * * *': every day at 02:00), got {value!r}")
        if len(value.split()) != 5:
            raise refusal
        try:
            CronSchedule(cron=value)
        except ValueError:
            raise refusal from None
        return value

    @field_validator("timezone")
    @classmethod
    def _timezone(cls, value: str) -> str:
        if value not in available_timezones():
            raise ValueError(f"unknown timezone {value!r} (an IANA name such as UTC or Europe/Berlin)")
        return value

    @model_validator(mode="after")
    def _distinct_ports(self) -> ServiceConfig:
        if len({self.prefect_port, self.mlflow_port, self.dashboard_port}) < 3:
            raise ValueError("the three ports must differ")
        return self

    def url(self, service: str) -> str:
        """Where `service` (prefect, mlflow or dashboard) answers."""
        return f"http://{HOST}:{getattr(self, f'{service}_port')}"
