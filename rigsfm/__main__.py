from rigsfm.cli import app

app(prog_name="rigsfm")
