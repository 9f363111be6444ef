"""METHOD stages 2-6: certainty grid, trajectories, feasibility, visibility, view graph, NMS."""
