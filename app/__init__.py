"""app: the composition root. The `palpate` CLI (app.cli and app.commands.*), the run orchestration
(app.commands.run) and the robot-cell script (app.cell). May import every library package; none imports it."""
