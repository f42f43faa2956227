"""What a run produces and how it is compared and exchanged: ship truth, scores, GIS exports."""
