"""Several robots into one map: the merge order, placing robots by shared places, the joint graph, the process."""
