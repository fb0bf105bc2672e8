from surgtrack.cli import app

app()
