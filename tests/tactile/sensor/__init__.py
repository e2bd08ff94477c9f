"""The virtual FSR array: imprints, the adaptive pad, settling, stiff contact, scale, extreme geometry, dead taxels."""
