"""The bot's backends behind `bot.Bot`: the simulated bot (and its camera), the serial
Farmduino (its client, the port's link, a virtual board, the simulated scan through it),
FarmBot's cloud (its credentials, its client, the bot), and the USB camera."""

#: How many times faster than real time the simulated scan through the serial backend runs
#: its virtual Farmduino (`serial_sim_bot.SimulatedSerialBot`): a 20-minute scan's motion
#: in 12 s, rendering aside.
SERIAL_SIM_TIME_SCALE = 100.0
