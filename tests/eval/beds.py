"""A small bed for the field-run tests: two easy plants 0.6 m apart, filmed at low
resolution and frame rate and along half the paper's rings, so a bed runs in under a
minute."""

BED = """[scan.path]
cylinder_radius_m = 0.3
cylinder_step_m = 0.04

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
