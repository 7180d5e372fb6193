"""FarmBot's cloud client (PyPI `farmbot`, 2.x) as this project uses it: made on first use,
its MQTT connections tried over TLS first, and found again to check or close them.

farmbot 2.x connects each command group to the broker on port 1883 in the clear, with the
bot's token as the MQTT password; `secure_broker` replaces that connect, process-wide, with
one that tries TLS on 8883 first (`connect_broker`).
"""

from __future__ import annotations

from typing import Any

from flowerpose.errors import InputError
from flowerpose.log import LOG


def farmbot_client() -> Any:
    """A new farmbot.Farmbot client (the package is imported on first use)."""
    try:
        from farmbot import Farmbot
    except ImportError:
        raise InputError("farmbot", "the FarmBot cloud client is not installed: "
                         "pip install 'farmbot>=2,<3'") from None
    return Farmbot()


#: MQTT over TLS (the broker's standard port for it); plain MQTT is 1883.
MQTT_TLS_PORT = 8883
MQTT_PLAIN_PORT = 1883
#: Brokers this process already warned about (one warning for all the client's connections).
_PLAIN_BROKERS: set[str] = set()


def connect_broker(self) -> None:
    """farmbot 2.x's BrokerConnect.connect with TLS: its own connects on port 1883 in the
    clear, with the bot's token as the MQTT password. TLS on 8883 first, with the system's
    certificate authorities; a broker that offers none (its TLS port refuses or times out)
    gets plain MQTT and one warning a process; a certificate that does not verify is an
    error, never a reason to drop to plain."""
    import ssl

    import paho.mqtt.client as mqtt

    self.state.check_token()
    token = self.state.token["token"]
    host = token["unencoded"]["mqtt"]

    def on_connect(_client, _obj, _flags, reason_code, _properties=None):
        status = str(reason_code)
        self.state.print_status(description=status)
        self.state.error = status if reason_code.is_failure else None

    def client() -> Any:
        made = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2)
        made.username_pw_set(username=token["unencoded"]["bot"], password=token["encoded"])
        made.on_connect = on_connect
        return made

    self.client = client()
    try:
        self.client.tls_set(cert_reqs=ssl.CERT_REQUIRED)
        self.client.connect(host, port=MQTT_TLS_PORT, keepalive=60)
    except ssl.SSLCertVerificationError as err:
        raise ConnectionError(f"MQTT broker {host}:{MQTT_TLS_PORT}: its TLS certificate did "
                              f"not verify ({err.verify_message})") from None
    except (OSError, ssl.SSLError, ValueError) as err:
        if host not in _PLAIN_BROKERS:
            LOG.warning(f"warning: MQTT broker {host}: no TLS on port {MQTT_TLS_PORT} "
                        f"({type(err).__name__}); connecting in the clear on "
                        f"{MQTT_PLAIN_PORT}, so the token crosses the network unencrypted")
        _PLAIN_BROKERS.add(host)
        self.client = client()
        self.client.connect(host, port=MQTT_PLAIN_PORT, keepalive=60)
    self.client.loop_start()
    self.state.print_status(description="Connected to message broker.")


def secure_broker() -> None:
    """Make every farmbot 2.x broker connection in this process try TLS first
    (`connect_broker`): the client opens one per command group, all through this class."""
    try:
        from farmbot.functions.broker import BrokerConnect
    except ImportError:
        return
    BrokerConnect.connect = connect_broker


def _brokers(client: Any) -> list[Any]:
    """The broker connections a client opened: farmbot 2.x opens one per command group
    (basic, movements, peripherals, information, ...) on its first use."""
    seen: dict[int, Any] = {}
    for part in [client, *getattr(client, "__dict__", {}).values()]:
        for holder in (part, getattr(part, "info", None)):
            broker = getattr(holder, "broker", None)
            if broker is not None and getattr(broker, "client", None) is not None:
                seen.setdefault(id(broker), broker)
    return list(seen.values())


def broker_lost(client: Any) -> bool:
    """Whether a broker connection the client opened is down now (paho reconnects by
    itself, so a reply that never came over a dropped link reads as a plain timeout)."""
    return any(not broker.client.is_connected() for broker in _brokers(client)
               if callable(getattr(broker.client, "is_connected", None)))


def disconnect(client: Any) -> None:
    """Close the MQTT connections a client opened (`_brokers`)."""
    for broker in _brokers(client):
        try:
            broker.disconnect()
        except Exception:  # noqa: BLE001 - closing must go on with the others
            pass
