"""Population algorithms as a table: name -> an :class:`~atdrone.population.base.Algorithm` class.

Each is a module with its own typed config section and one ``generation`` method
(see :mod:`atdrone.population.base`); the pure maths (the HOLA hypergraph
functions) sits beside them. Adding an algorithm is one module and one entry here.
"""

from atdrone.population.base import Algorithm
from atdrone.population.br import BestResponse
from atdrone.population.fcp import FCP
from atdrone.population.hola import Hola, HolaNoG
from atdrone.population.pbt import PBT
from atdrone.population.sp import SelfPlay
from atdrone.population.teammate import MAPPO, NahtD, NahtDNoDec

ALGORITHMS: dict[str, type[Algorithm]] = {
    "sp": SelfPlay,
    "br": BestResponse,
    "pbt": PBT,
    "hola": Hola,
    "hola_no_g": HolaNoG,
    "mappo": MAPPO,
    "naht_d": NahtD,
    "naht_d_no_dec": NahtDNoDec,
    "fcp": FCP,
}

__all__ = ["ALGORITHMS", "Algorithm"]
