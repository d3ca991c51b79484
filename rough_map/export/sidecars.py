"""Files beside a class GeoTIFF that GIS tools read natively: category names and a style.

A GeoTIFF has no place for the names of the values of a band, so GDAL keeps them in its
PAM side-car ``<file>.tif.aux.xml``, which every GDAL-based tool (QGIS, ``gdalinfo``,
rasterio) reads when it opens the GeoTIFF:

* ``<CategoryNames>``: the name of each value, 0, 1, ... (``gdalinfo`` lists them under
  "Categories"; ``GDALGetRasterCategoryNames``);
* ``<GDALRasterAttributeTable>``: a thematic raster attribute table, one row per class with
  its value, name and colour (QGIS shows the names in the layer's legend and identify
  tool).

QGIS also loads a style file of the same base name beside a raster: ``<file>.qml`` holds a
paletted renderer with each class's colour and name, so the map opens coloured and labelled.

Both are written atomically; unknown cells (nodata 255) have no category.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from xml.sax.saxutils import escape, quoteattr

from rough_map._files import atomic_output
from rough_map.errors import InputError

__all__ = ["write_category_names", "write_qgis_style"]

# GDAL's RAT field types and usages (gdal.h: GDALRATFieldType, GDALRATFieldUsage)
_GFT_INTEGER, _GFT_STRING = 0, 2
_GFU_GENERIC, _GFU_NAME, _GFU_MIN_MAX = 0, 2, 5
_GFU_RED, _GFU_GREEN, _GFU_BLUE = 6, 7, 8


def _check(names: Sequence[str], colours: Sequence[Sequence[int]]) -> None:
    if not names or len(names) != len(colours):
        raise InputError(f"{len(names)} class names for {len(colours)} colours")


def write_category_names(
    tif: str | Path, names: Sequence[str], colours: Sequence[Sequence[int]]
) -> Path:
    """Write ``<tif>.aux.xml``: the category names and a raster attribute table of band 1.

    Parameters
    ----------
    tif : str or Path
        The class GeoTIFF (values 0 .. len(names) - 1).
    names : sequence of str
        The name of each value.
    colours : sequence of (r, g, b)
        The colour of each value, 0-255.

    Returns
    -------
    Path
        The ``.aux.xml`` file.
    """
    _check(names, colours)
    fields = [("Value", _GFT_INTEGER, _GFU_MIN_MAX), ("class", _GFT_STRING, _GFU_NAME),
              ("Red", _GFT_INTEGER, _GFU_RED), ("Green", _GFT_INTEGER, _GFU_GREEN),
              ("Blue", _GFT_INTEGER, _GFU_BLUE)]  # fmt: skip
    lines = [
        "<PAMDataset>",
        '  <PAMRasterBand band="1">',
        "    <CategoryNames>",
        *(f"      <Category>{escape(n)}</Category>" for n in names),
        "    </CategoryNames>",
        '    <GDALRasterAttributeTable tableType="thematic">',
        *(
            f'      <FieldDefn index="{i}"><Name>{name}</Name><Type>{kind}</Type>'
            f"<Usage>{usage}</Usage></FieldDefn>"
            for i, (name, kind, usage) in enumerate(fields)
        ),
        *(
            f'      <Row index="{i}"><F>{i}</F><F>{escape(n)}</F>'
            + "".join(f"<F>{int(v)}</F>" for v in rgb[:3])
            + "</Row>"
            for i, (n, rgb) in enumerate(zip(names, colours, strict=True))
        ),
        "    </GDALRasterAttributeTable>",
        "  </PAMRasterBand>",
        "</PAMDataset>",
    ]
    path = Path(f"{tif}.aux.xml")
    with atomic_output(path) as tmp:
        Path(tmp).write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def write_qgis_style(
    tif: str | Path, names: Sequence[str], colours: Sequence[Sequence[int]]
) -> Path:
    """Write ``<tif stem>.qml``, a QGIS paletted style naming and colouring each class.

    Parameters are those of :func:`write_category_names`; returns the ``.qml`` file.
    """
    _check(names, colours)
    entries = "\n".join(
        f'        <paletteEntry value="{i}" alpha="255" '
        f'color="#{int(rgb[0]):02x}{int(rgb[1]):02x}{int(rgb[2]):02x}" label={quoteattr(n)}/>'
        for i, (n, rgb) in enumerate(zip(names, colours, strict=True))
    )
    text = f"""<!DOCTYPE qgis PUBLIC 'http://mrcc.com/qgis.dtd' 'SYSTEM'>
<qgis version="3.28" styleCategories="Symbology">
  <pipe>
    <rasterrenderer type="paletted" band="1" opacity="1" alphaBand="-1" nodataColor="">
      <rasterTransparency/>
      <colorPalette>
{entries}
      </colorPalette>
    </rasterrenderer>
  </pipe>
</qgis>
"""
    path = Path(tif).with_suffix(".qml")
    with atomic_output(path) as tmp:
        Path(tmp).write_text(text, encoding="utf-8")
    return path
