"""Robot-suite code shared by the eval/ entry scripts: robosuite tasks, scripted experts, robomimic hdf5
I/O, batched rollouts and recorded trajectories."""
