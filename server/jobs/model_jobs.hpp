#pragma once

#include <cstdint>
#include <filesystem>
#include <string>

#include "core/io/grid_source.hpp"
#include "server/jobs/job_registry.hpp"
#include "server/models/model_registry.hpp"

namespace vsm::server::jobs {

/// Submits an import: `input` (a raster or organized point cloud inside the data root, resolved
/// already) is built into the OPC directory <data root>/<id> with `patchSize` vertices per side
/// (importFile) and `drape` (ShadedRelief or None), which is then opened as model `id`. The id is
/// reserved until the job ends.
///
/// `visibleTexelsPerQuad`: hidden levels below it (ImportOptions::visibleTexelsPerQuad; 0: none).
///
/// Throws core::Error(InvalidArgument) for a bad id, patch size or visible texels per quad
/// (a power of two whose tiles stay within kMaxTextureTileSize, and not with Drape::None),
/// Conflict when the id is open
/// or reserved or <data root>/<id> exists, Unavailable when the job queue is full.
JobStatus submitImport(JobRegistry& jobs, models::ModelRegistry& models, const std::string& id,
                       const std::filesystem::path& input, int patchSize,
                       core::ImportOptions::Drape drape, int visibleTexelsPerQuad = 0);

/// Submits a merge of the open model `source` (the detail) into the open model `target`
/// (DESIGN.md section 3): target->beginEdit(), registerModels() when `registerFirst`,
/// mergeModels(), publish(). Readers see the old version until publish() returns and the new one
/// after; on error or cancellation the edit is discarded. Both models are leased (cannot be
/// closed) until the job ends. Jobs writing one model (merges into it, restores of it) run one
/// at a time in submission order, each on the model's opening current when it starts.
///
/// Throws core::Error(InvalidArgument) when target == source, NotFound for a model that is not
/// open, Conflict for a target open for reading only, Unavailable when the job queue is full.
JobStatus submitMerge(JobRegistry& jobs, models::ModelRegistry& models, const std::string& target,
                      const std::string& source, bool registerFirst);

/// Submits a restore: publishes the content of kept revision `revision` of the open model `id` as
/// its next revision (ModelEdit::restore; the revision record names it). The model is leased until
/// the job ends.
///
/// Throws core::Error(NotFound) for a model not open or a revision not kept, Conflict for a model
/// open for reading only, Unavailable when the job queue is full.
JobStatus submitRestore(JobRegistry& jobs, models::ModelRegistry& models, const std::string& id,
                        std::uint64_t revision);

}  // namespace vsm::server::jobs
