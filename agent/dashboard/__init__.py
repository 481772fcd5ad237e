"""The live dashboard: a web page, served by its own process, that shows the avatar, both transcripts,
voice activity and turns, live latency and drop counters, with Start/Stop controls. Nothing leaves the machine.

- `config.DashboardConfig`: the `dashboard:` options.
- `launcher.DashboardProcess`: what the supervisor starts and watches.
- `process`: the process (bus subscriber + aiohttp server); `events`: bus messages -> page events.
- `server`: HTTP + WebSocket; `static/`: the page (plain HTML/CSS/JS, no build step, no CDN).
- `browser`: a minimal headless-Chromium driver (DevTools protocol) for tests and screenshots.
"""
