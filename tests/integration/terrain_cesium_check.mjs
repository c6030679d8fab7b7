// CesiumJS's own CesiumTerrainProvider (the npm package, in Node: no browser, no rendering) reads
// vsmd's terrain: layer.json, then tiles as it asks for them (its Accept header, its decoder),
// and sampleTerrainMostDetailed answers heights at the given points. Prints one JSON object.
//
//   node terrain_cesium_check.mjs <node_modules/cesium> <.../terrain/ URL> <points.json>
import fs from "node:fs";
import path from "node:path";
import { pathToFileURL } from "node:url";

const [cesiumDir, url, pointsFile] = process.argv.slice(2);
const Cesium = await import(pathToFileURL(path.join(cesiumDir, "Source", "Cesium.js")).href);

const provider = await Cesium.CesiumTerrainProvider.fromUrl(url, {
  requestVertexNormals: true,
  requestMetadata: true,
});
const errors = [];
provider.errorEvent.addEventListener((e) => errors.push(String(e.message ?? e)));

const points = JSON.parse(fs.readFileSync(pointsFile, "utf8"));
const cartographics = points.map(([lon, lat]) => Cesium.Cartographic.fromDegrees(lon, lat));
// rejectOnTileFail: a tile that fails to load or decode fails the whole call.
const sampled = await Cesium.sampleTerrainMostDetailed(provider, cartographics, true);

// The two root tiles, decoded by CesiumJS, with their normals.
const roots = [];
for (const x of [0, 1]) {
  const data = await provider.requestTileGeometry(x, 0, 0);
  roots.push({
    x,
    minimumHeight: data._minimumHeight,
    maximumHeight: data._maximumHeight,
    vertices: data._quantizedVertices.length / 3,
    normals: data._encodedNormals ? data._encodedNormals.length / 2 : 0,
  });
}

console.log(
  JSON.stringify({
    hasVertexNormals: provider.hasVertexNormals,
    hasMetadata: provider.hasMetadata,
    errors,
    heights: sampled.map((c) => c.height),
    levels: cartographics.map((c) => provider.availability.computeMaximumLevelAtPosition(c)),
    roots,
  }),
);
