"""Building blocks of discrete mechanics: parameterisations, kinetic terms, potentials, forces."""
