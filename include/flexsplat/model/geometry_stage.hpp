#pragma once
// The geometry stage of FlexSplat: VGGT on the input images (training forward with its cache), its outputs turned
// into the library's conventions (GeometryResult: pixel centres at +0.5), and the way back: gradients with respect
// to GeometryResult and the pose encodings into VGGT's parameter gradients.
#include <algorithm>
#include <vector>

#include "flexsplat/geometry/vggt.hpp"
#include "flexsplat/model/cameras.hpp"
#include "flexsplat/model/geometry_result.hpp"
#include "flexsplat/model/weights.hpp"

namespace flexsplat {
inline namespace v0 {
namespace model {

template <class T>
struct GeometryStage {
  GeometryResult<T> result;
  std::vector<T> pose_enc;  // [iterations, V, 9] every refinement iteration's encoding (the last is the prediction)
  index_t iterations = 0;
  geometry::VggtOutputs<T> outputs;
  geometry::VggtCache<T> cache;
  geometry::VggtWorkspace<T> workspace;
  geometry::VggtBackwardScratch<T> scratch;
  std::vector<T> d_intrinsics;
  bool recompute = false;  // rerun each transformer block in backward instead of storing its activations
  // [iterations - 1, V, 9] raw encodings the camera head feeds back instead of its own (null: its own). VGGT detaches
  // the feedback, so a finite-difference check must hold it fixed to see the gradient backward computes.
  const T* camera_feedback = nullptr;
};

// images [V, 3, h, w] in [0, 1] at the configuration's size. train: keep what backward needs.
template <class T>
void geometry_stage_forward(GeometryStage<T>& st, const FlexSplatWeights<T>& w, const T* images, index_t views,
                            bool train = true) {
  const FlexSplatConfig& c = w.config();
  const index_t h = c.image_h, wd = c.image_w;
  geometry::VggtOptions opt;
  opt.keep_depth_features = true;
  if (train) {
    geometry::VggtTrainOptions<T> to;
    to.recompute = st.recompute;
    to.camera_feedback = st.camera_feedback;
    st.outputs = geometry::vggt_forward_train<T>(images, views, h, wd, c.geometry, w.geometry(), st.cache,
                                                 st.workspace, to, opt);
  } else {
    st.outputs = geometry::vggt_forward<T>(images, views, h, wd, c.geometry, w.geometry(), st.workspace, opt);
  }
  const auto& o = st.outputs;
  const index_t fc = c.geometry.depth.head_features();
  GeometryResult<T>& g = st.result;
  g.resize(views, h, wd, fc, h, wd);
  std::copy(o.extrinsics.data(), o.extrinsics.data() + 12 * views, g.extrinsics.begin());
  intrinsics_from_vggt(g.K.data(), o.intrinsics.data(), views);
  std::copy(o.depth.data(), o.depth.data() + views * h * wd, g.depth.begin());
  std::copy(o.depth_conf.data(), o.depth_conf.data() + views * h * wd, g.confidence.begin());
  std::copy(o.depth_features.data(), o.depth_features.data() + views * fc * h * wd, g.features.begin());
  st.iterations = c.geometry.camera.iterations;
  st.pose_enc.assign(o.pose_enc.data(), o.pose_enc.data() + st.iterations * views * geometry::pose_encoding_dim);
}

// d_result: gradients with respect to st.result (any field may be all zero); d_pose_enc [iterations, V, 9], d_points
// [V, h, w, 3] and d_points_conf [V, h, w] (point head), d_descriptors [V, h, w, match_dim] and d_foreground [V, h, w]
// (match head) may be null. Adds into the VGGT tensors of `grads`, a gradient
// block laid out like the store's params.
template <class T>
void geometry_stage_backward(GeometryStage<T>& st, const FlexSplatWeights<T>& w, T* grads,
                             const GeometryResult<T>& d_result, const T* d_pose_enc, const T* d_points = nullptr,
                             const T* d_points_conf = nullptr, const T* d_descriptors = nullptr,
                             const T* d_foreground = nullptr) {
  const FlexSplatConfig& c = w.config();
  const index_t V = st.result.views;
  st.d_intrinsics.assign(static_cast<std::size_t>(9 * V), T(0));
  intrinsics_from_vggt_backward(st.d_intrinsics.data(), d_result.K.data(), V);
  geometry::VggtOutputGrads<T> d;
  d.pose_enc = d_pose_enc;
  d.extrinsics = d_result.extrinsics.data();
  d.intrinsics = st.d_intrinsics.data();
  d.depth = d_result.depth.data();
  d.depth_conf = d_result.confidence.data();
  d.depth_features = d_result.features.data();
  d.points = d_points;
  d.points_conf = d_points_conf;
  d.descriptors = d_descriptors;
  d.foreground = d_foreground;
  const auto g = geometry::vggt_grads(w.geometry(), w.store().params(), grads);
  geometry::vggt_backward<T>(static_cast<T*>(nullptr), g, d, st.outputs, st.cache, c.geometry, w.geometry(), st.scratch);
}

}  // namespace model
}  // namespace v0
}  // namespace flexsplat
