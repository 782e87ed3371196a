"""Code generation: the C formatting, the Jinja environment, the renderer over the actor kinds'
descriptions, the dense-layer kernel's arrays and AVR assembly, the flash / SRAM budget, the manifest."""
