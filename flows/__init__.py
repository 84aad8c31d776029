"""Prefect flows and the `sim2act` command: composition only; the logic lives in stages/."""
