"""The simulated G1 behind the executor's interface: MuJoCo model with the people in it
(:mod:`.sim`), and the executor that steps it (:mod:`.executor`)."""
