"""A small bed for the field-run tests: two easy plants 0.6 m apart, filmed at low
resolution and frame rate so a bed runs in about a minute."""

BED = """[scan.path]
cylinder_radius_m = 0.3

[[plant]]
name = "a"
x = 1.0
y = 0.75

[[plant]]
name = "b"
x = 1.6
y = 0.75
"""
SMALL = ["--preset", "easy", "--set", "scan.camera.width=480", "--set",
         "scan.camera.height=270", "--set", "scan.camera.frame_rate_hz=0.04", "--set",
         "scan.frames.count=60"]
