"""The supervisor's side of the dashboard: start its process, read the page's Start/Stop, notice if it dies.

dashboard = DashboardProcess.start(app, run, ipc_dir)   # None when dashboard.enabled is false
subscriber addresses += [dashboard.address]
dashboard.on_control(msg)        # a Control from source "dashboard" -> sets start_requested / stop_requested
dashboard.process, .log_path     # to notice that it died, and to terminate it with the stages
"""

from __future__ import annotations

import logging
import multiprocessing as mp
from pathlib import Path

from agent.dashboard.access import new_token
from agent.dashboard.process import DASHBOARD, DashboardLaunch, dashboard_main, page_url
from agent.sections import AppConfig
from ecas.core.bus import stage_address
from ecas.core.component import RunContext
from ecas.core.messages import Command, Control

log = logging.getLogger(DASHBOARD)


class DashboardProcess:
    def __init__(self, process: mp.Process, address: str, log_path: Path):
        self.process, self.address, self.log_path = process, address, log_path
        self.start_requested = False
        self.stop_requested = False

    @classmethod
    def start(cls, app: AppConfig, run: RunContext, ipc_dir: Path) -> DashboardProcess | None:
        cfg = app.dashboard
        if not cfg.enabled:
            return None
        token = None if cfg.loopback_only else new_token()
        if token:
            log.warning(
                "the dashboard listens on %s:%d (dashboard.host / --host): anyone who can reach this machine and "
                "has the URL below, with its token, can watch the conversation and start or stop the agent",
                cfg.host,
                cfg.port,
            )
        launch = DashboardLaunch(app, run, ipc_dir, token)
        process = mp.get_context("spawn").Process(target=dashboard_main, args=(launch,), name=DASHBOARD)
        process.start()
        tls = cfg.tls_cert is not None
        shown = page_url(cfg.host, cfg.port, tls, token) if cfg.port else f"see {run.run_dir / 'dashboard.url'}"
        log.info("dashboard: %s%s", shown, " (the run waits for its Start button)" if cfg.wait_for_start else "")
        return cls(process, stage_address(DASHBOARD, app.bus, ipc_dir), launch.log_path)

    def on_control(self, msg: Control) -> None:
        if msg.command == Command.START:
            self.start_requested = True
        elif msg.command == Command.STOP:
            self.stop_requested = True
