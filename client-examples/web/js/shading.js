// The sun: one direction per point, in that point's own east-north-up frame, as a hillshade has
// it (one fixed direction would light a model the size of the US differently in the east and the
// west). A surface facing it is lit fully, one facing away gets AMBIENT of its colour.
// A model in a local frame (no georeference: a tunnel, a rock face) has no geocentric up: there up
// is the frame's +z, and a surface is lit on the side the camera sees (from inside a tunnel the
// ceiling faces down, and is still lit when the sun is behind it).

import * as THREE from 'three';
import { state } from './settings.js';
import { invalidate } from './frames.js';

/// The share of its colour a surface facing away from the sun keeps.
const AMBIENT = 0.2;

/// The sun as a uniform all lit materials share (radians: azimuth, altitude).
const sunUniform = { value: new THREE.Vector2() };
/// 1 for an earth-centred model (up geocentric, normals turned up), 0 for a local frame.
const earthUniform = { value: 1 };

/// Azimuth (degrees clockwise from north) and altitude (degrees above the horizon).
export function setSun(azimuth, altitude) {
  sunUniform.value.set(THREE.MathUtils.degToRad(azimuth), THREE.MathUtils.degToRad(altitude));
  state.sun = { azimuth, altitude };
  invalidate();
}

/// The frame of the model shown: earth-centred (ECEF) or local.
export function setEarthCentred(earthCentred) {
  earthUniform.value = earthCentred ? 1 : 0;
  invalidate();
}

const SUN_VERTEX = `
varying vec3 vNormal;
varying vec3 vWorld;
#ifdef VSM_MAP
varying vec2 vUv;
#endif
void main() {
  vWorld = (modelMatrix * vec4(position, 1.0)).xyz;
  vNormal = mat3(modelMatrix) * normal;
#ifdef VSM_MAP
  vUv = uv;
#endif
  gl_Position = projectionMatrix * modelViewMatrix * vec4(position, 1.0);
}`;

// Up is the geocentric direction (within 0.2 degrees of the ellipsoid's normal), east and north
// follow from it; normals are turned to face up (a terrain's triangles may wind either way). In a
// local frame up is +z (east +x) and normals are turned to face the camera.
const SUN_FRAGMENT = `
uniform vec3 colour;
uniform vec2 sun;
uniform float ambient;
uniform float earth;
#ifdef VSM_MAP
uniform sampler2D map;
varying vec2 vUv;
#endif
varying vec3 vNormal;
varying vec3 vWorld;
void main() {
  vec3 up = earth > 0.5 ? normalize(vWorld) : vec3(0.0, 0.0, 1.0);
  vec3 east = earth > 0.5 ? normalize(vec3(-up.y, up.x, 0.0)) : vec3(1.0, 0.0, 0.0);
  vec3 north = cross(up, east);
  vec3 light = cos(sun.y) * (sin(sun.x) * east + cos(sun.x) * north) + sin(sun.y) * up;
  vec3 n = normalize(vNormal);
  vec3 facing = earth > 0.5 ? up : cameraPosition - vWorld;
  n = dot(n, facing) < 0.0 ? -n : n;
  float shade = ambient + (1.0 - ambient) * max(dot(n, light), 0.0);
  vec4 c = vec4(colour, 1.0);
#ifdef VSM_MAP
  c *= texture2D(map, vUv);
#endif
  gl_FragColor = vec4(c.rgb * shade, c.a);
  #include <colorspace_fragment>
}`;

/// A material lit by the sun: `colour` (sRGB), times `map` when given.
export function sunMaterial(colour, map = null) {
  return new THREE.ShaderMaterial({
    uniforms: {
      colour: { value: new THREE.Color(colour) },
      sun: sunUniform,
      earth: earthUniform,
      ambient: { value: AMBIENT },
      map: { value: map },
    },
    defines: map ? { VSM_MAP: '' } : {},
    vertexShader: SUN_VERTEX,
    fragmentShader: SUN_FRAGMENT,
    side: THREE.DoubleSide,
  });
}
