"""Pollination visits in the simulator: the bot and plant in MuJoCo contact, each visit flown
and judged, and how far off a flower's axis a visit may come."""
