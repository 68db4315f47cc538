"""The simulated G1 behind the executor's interface: the MuJoCo model with the people in it
(:mod:`.model`), its contact computations (:mod:`.contacts`), the simulation that holds its state
and steps it (:mod:`.sim`), and the executor around the simulation (:mod:`.executor`). The model and
contact computations do not import the simulation or the executor."""
