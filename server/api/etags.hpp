#pragma once

#include <cstdint>
#include <span>
#include <string>
#include <string_view>

#include "core/pyramid/patch_key.hpp"

namespace vsm::core {
class Model;
struct ModelSnapshot;
struct PatchInfo;
}  // namespace vsm::core

namespace vsm::server::api {

/// Every entity tag of the model routes, in one place: what a tag is derived from decides when
/// clients revalidate, so the derivations are kept side by side.

/// Bumped whenever the GLB encoder or tilesetJson() change what they produce for the same model,
/// so clients holding the old bytes under an ETag revalidate to the new ones.
/// t2: textures embedded; t3: meshopt-compressed content by default, per-variant tags; t4: the
/// tileset names its model version (asset.extras.model_version).
inline constexpr std::string_view kTilesFormat = "t4";

/// A model's published metadata (summary, hierarchy, LOD cuts): the snapshot's digest of every
/// patch's key, version, folder, children, box and Local2Global (core::modelDigest, kept by the
/// change from publish to publish). Derived from content rather than from the snapshot's version,
/// which restarts at 1 whenever the model is opened.
std::string modelEtag(const core::ModelSnapshot& snapshot);
/// A view of the model chosen by a query (`view` "h": hierarchy, "l": LOD cut).
std::string viewEtag(const core::ModelSnapshot& snapshot, std::string_view view,
                     std::string_view query);
/// One patch (metadata and positions): key, patch version (persisted in the OPC) and a digest of
/// its metadata.
std::string patchEtag(const core::PatchInfo& info);
/// Other data of one patch: its tag with `suffix` ("uv": coordinates, "png": texture).
std::string patchDataEtag(const core::PatchInfo& info, std::string_view suffix);
/// A model's tileset and one patch's GLB: the model's and the patch's tags with kTilesFormat and
/// `variant`, which names the representation ("" for the default: compressed content, identity
/// transfer; e.g. "raw" for uncompressed content, "gz" for a gzipped body), so that no two
/// representations share a tag.
std::string tilesetEtag(const core::ModelSnapshot& snapshot, std::string_view variant = {});
std::string glbEtag(const core::PatchInfo& info, std::string_view variant = {});
/// Bumped whenever the quantized-mesh encoder (core/tiles/quantized_mesh) or layer.json change
/// what they produce for the same model. q2: layer.json's tile URLs name the model version
/// ("?v=12", no longer CesiumJS's "{version}" template, which it filled with "1.0.0").
inline constexpr std::string_view kTerrainFormat = "q2";
/// A terrain tile's content version (quantized-mesh or terrain-RGB): a digest of the tile, the
/// key and version in `model` of every patch it is sampled from (core::terrainSources,
/// core::demTileSources), kTerrainFormat and `variant` (the representation: extensions, the
/// metadata extension's text, content coding, encoding). Also its key in the encoded-response
/// cache.
std::uint64_t terrainVersion(std::string_view tile, const core::Model& model,
                             std::span<const core::PatchKey> sources, std::string_view variant);
/// The tag of a terrain tile of that version.
std::string terrainEtag(std::string_view tile, std::uint64_t version);
/// A static file (the viewer's): its size, modification time (ns) and inode.
std::string staticFileEtag(std::uint64_t size, std::uint64_t mtimeNs, std::uint64_t inode);

}  // namespace vsm::server::api
