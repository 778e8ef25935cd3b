"""Language interface (DESIGN.md): a sentence becomes a checked guidance loss."""
