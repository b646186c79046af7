"""Two image grids side by side, each enlarged 2x without smoothing, under a label each:
   side_by_side.py LEFT.png RIGHT.png OUT.png "left label" "right label"
Written through a temporary name, so an interrupted run never leaves half a figure."""
import os
import sys

from PIL import Image, ImageDraw

left, right, out, left_label, right_label = sys.argv[1:6]
a, b = (Image.open(p).convert("RGB") for p in (left, right))
a, b = (im.resize((im.width * 2, im.height * 2), Image.NEAREST) for im in (a, b))
gap, head = 16, 24
fig = Image.new("RGB", (a.width + gap + b.width, head + max(a.height, b.height)), "white")
fig.paste(a, (0, head))
fig.paste(b, (a.width + gap, head))
draw = ImageDraw.Draw(fig)
for x, text in ((0, left_label), (a.width + gap, right_label)):
    draw.text((x + 4, 6), text, fill="black")
fig.save(out + ".tmp.png")
os.replace(out + ".tmp.png", out)
