"""Parameter names: the authors' release (state-dict keys) ↔ gdrf checkpoints."""
import re

_RULES = [
    (r"^siren\.network\.(\d+)\.layer\.(weight|bias)$", r"template.trunk.\1.\2"),
    (r"^siren\.final_layer\.(weight|bias)$", r"template.sigma_head.\1"),
    (r"^siren\.color_network\.(\d+)\.layer\.(weight|bias)$", r"template.color.\1.\2"),
    (r"^siren\.color_layer_linear\.0\.(weight|bias)$", r"template.rgb_head.\1"),
    (r"^siren\.mapping_network\.network\.([0246])\.(weight|bias)$", "appearance_mapping.{m}.\\2"),
    (r"^deformnet\.siren\.network\.(\d+)\.layer\.(weight|bias)$", r"deform.film.\1.\2"),
    (r"^deformnet\.siren\.final_layer\.(weight|bias)$", r"deform.head.\1"),
    (r"^deformnet\.siren\.mapping_network\.network\.([0246])\.(weight|bias)$", "shape_mapping.{m}.\\2"),
]


def release_to_gdrf(name):
    """The gdrf name of a release parameter, or None for a key gdrf does not use."""
    for pattern, repl in _RULES:
        m = re.match(pattern, name)
        if m:
            if "{m}" in repl:
                repl = repl.replace("{m}", str(int(m.group(1)) // 2))
            return m.expand(repl)
    return None


def release_parameter_order(trunk=5, color=4, deform=4):
    """The order of generator.parameters() in the release (maps EMA shadow lists)."""
    names = []
    wb = ("weight", "bias")
    names += [f"siren.network.{i}.layer.{p}" for i in range(trunk) for p in wb]
    names += [f"siren.final_layer.{p}" for p in wb]
    names += [f"siren.color_network.{i}.layer.{p}" for i in range(color) for p in wb]
    names += [f"siren.color_layer_linear.0.{p}" for p in wb]
    names += [f"siren.mapping_network.network.{i}.{p}" for i in (0, 2, 4, 6) for p in wb]
    names += [f"deformnet.siren.network.{i}.layer.{p}" for i in range(deform) for p in wb]
    names += [f"deformnet.siren.final_layer.{p}" for p in wb]
    names += [f"deformnet.siren.mapping_network.network.{i}.{p}" for i in (0, 2, 4, 6) for p in wb]
    return names
