from calibcoach.app.cli import run

run()
