"""The bot's backends behind `bot.Bot`: the simulated bot (and its camera), the serial
Farmduino (its client, the port's link, a virtual board, the simulated scan through it),
FarmBot's cloud (its credentials, its client, the bot), and the USB camera."""
