"""The core every package may import: time constants, body constants, condition spec, messages, the bus, the
config loader and a component's view of the run. It imports no stage (no `agent`, `dialogue`, `gesture` or
`render` module)."""
