"""Motion design: plans A-E, commands by inverse response or through the face model, evaluation."""
