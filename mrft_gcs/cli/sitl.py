"""``mrft-tune sitl``: serve the bundled simulated vehicle over MAVLink/UDP."""

from __future__ import annotations

import signal
from pathlib import Path
from typing import Annotated

import typer
from rich.text import Text

from mrft_gcs.cli.app import app, console
from mrft_gcs.errors import UsageError
from mrft_gcs.sitl.population import domain_check
from mrft_gcs.sitl.process import DEFAULT_PORT, SitlConfig, make_server, parse_effects


@app.command()
def sitl(
    vehicle: Annotated[str | None, typer.Option(
        help="Bundled profile (qdrone, racer250, f550) or a path to a vehicle TOML "
             "[default: qdrone]; with --physics rotorpy a RotorPy parameter set "
             "(crazyfliebrushless, crazyflie, hummingbird) [default: crazyfliebrushless].")
    ] = None,
    port: Annotated[int, typer.Option(
        help="UDP port the ground station listens on; the SITL sends there.")] = DEFAULT_PORT,
    effect: Annotated[list[str] | None, typer.Option(
        help="Unmodelled effect NAME=VALUE, repeatable (e.g. sensor_lpf=30).")] = None,
    speedup: Annotated[float, typer.Option(
        help="Simulated seconds per wall second (1 = real time).")] = 1.0,
    seed: Annotated[int, typer.Option(help="Sensor-noise seed.")] = 0,
    signing_key: Annotated[Path | None, typer.Option(
        help="MAVLink 2 signing key file (32 bytes or 64 hex digits): unsigned commands "
             "and setpoints are then ignored.")] = None,
    random: Annotated[int | None, typer.Option(
        "--random", metavar="SEED",
        help="Fly a vehicle drawn at random from SEED (airframe, delays, onboard "
             "loops, telemetry rate; the same for the same SEED) instead of --vehicle.")
    ] = None,
    physics: Annotated[str, typer.Option(
        help="Rigid body, rotors and motors: 'native' (the project's) or 'rotorpy' (RotorPy, "
             "a third-party simulator; pip install 'mrft-gcs[test]'). Onboard software, "
             "sensors and MAVLink stay the project's.")] = "native",
) -> None:
    """Serve a simulated multirotor over MAVLink (UDP) until Ctrl-C.

    Example:  mrft-tune sitl --vehicle qdrone --port 14540 --effect sensor_lpf=30

    Example:  mrft-tune sitl --random 17     (a random vehicle; the same for the same seed)

    Example:  mrft-tune sitl --physics rotorpy --vehicle crazyfliebrushless
    """
    if random is not None and vehicle is not None:
        raise UsageError("give --vehicle or --random SEED, not both")
    cfg = SitlConfig(vehicle=vehicle, port=port, random_seed=random, speedup=speedup,
                     effects=parse_effects(effect or []), seed=seed,
                     signing_key_file=str(signing_key) if signing_key else None,
                     physics=physics)
    server = make_server(cfg)
    previous = signal.signal(signal.SIGTERM, lambda *_: server.stop())
    af = server.vehicle.airframe
    console.print(Text.assemble("SITL ", (af.name, "bold"),
                                f" ({af.description}) serving MAVLink 2 over UDP"))
    active = af.effects.active()
    if random is not None or physics != "native":
        check = domain_check(af)
        console.print(f"Table I domain: {check.category}"
                      + (f" ({'; '.join(check.reasons)})" if check.reasons else ""),
                      highlight=False)
    if active:
        console.print("effects: " + ", ".join(f"{k}={v:g}" for k, v in active.items()))
    console.print(Text.assemble("connect with:  ", (cfg.connection_string, "bold"),
                                f"   (MAVSDK: udpin://{cfg.host}:{cfg.port})   Ctrl-C to stop"),
                  highlight=False)
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        pass
    finally:
        signal.signal(signal.SIGTERM, previous)
        server.close()
