"""The domain core, standard library only: worlds and their generation, the variants table, the texts
(task, observations, cognitive maps, conversations), the environment, scoring and the scored episode."""
