"""The metric side of a PTM (thesis Ch. 5): pose graphs, smoothed and laser-refined trajectories of a
topology, occupancy grids with their nav2 map files and their quality against a reference, and the route
graph."""
