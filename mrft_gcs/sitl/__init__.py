"""The bundled simulated vehicle (SITL): physics, PX4-style onboard software, MAVLink over UDP.

``SitlProcess`` runs it as a subprocess (``python -m mrft_gcs.sitl``) for tests and the demo;
``SimVehicle`` steps it in-process without sockets; ``load_airframe`` reads a vehicle profile
from ``profiles/vehicles/NAME.toml``. See README section "SITL".
"""

from mrft_gcs.sitl.airframe import (
    EFFECT_NAMES,
    Airframe,
    Effects,
    OnboardSpec,
    available_vehicles,
    load_airframe,
)
from mrft_gcs.sitl.onboard import CommandResult, FlightMode
from mrft_gcs.sitl.physics import Measurement, Multirotor
from mrft_gcs.sitl.population import DomainCheck, domain_check, random_airframe
from mrft_gcs.sitl.process import DEFAULT_PORT, SitlProcess
from mrft_gcs.sitl.vehicle import SimVehicle

__all__ = [
    "Airframe",
    "Effects",
    "EFFECT_NAMES",
    "OnboardSpec",
    "random_airframe",
    "domain_check",
    "DomainCheck",
    "load_airframe",
    "available_vehicles",
    "Multirotor",
    "Measurement",
    "SimVehicle",
    "FlightMode",
    "CommandResult",
    "SitlProcess",
    "DEFAULT_PORT",
]
