#pragma once
// Data parallelism with results independent of the process count. The global batch's per-scene gradients are summed
// sequentially in global scene order: the running sum passes from the rank of scene s to the rank of scene s + 1
// whenever they differ, each rank adding its own scenes in order; the rank of the last scene broadcasts the total.
// One process runs the same additions in the same order, so N ranks give bit-identical parameters to one process with
// the same global batch, however the scenes are spread over the ranks (ScenePlan). The chain costs one message of the
// gradient size per change of rank along the batch, which suits the few-node clusters this targets; MPI's tree
// reductions would be faster but their order depends on the rank count.
//
// MPI is optional: MpiCommunicator exists only where the including target defines FLEXSPLAT_WITH_MPI and links MPI
// (the build's FLEXSPLAT_MPI option does that for the command-line program and tests).
#include <algorithm>
#include <climits>
#include <cstddef>
#include <cstring>
#include <numeric>
#include <span>
#include <vector>

#include "flexsplat/core/error.hpp"
#include "flexsplat/core/tensor.hpp"

#if defined(FLEXSPLAT_WITH_MPI)
#include <mpi.h>
#endif

namespace flexsplat {
inline namespace v0 {
namespace train {

class Communicator {
public:
  virtual ~Communicator() = default;
  virtual int rank() const = 0;
  virtual int size() const = 0;
  // Blocking point-to-point copies of `bytes` bytes, matched in the order they are posted.
  virtual void send_bytes(const void* data, std::size_t bytes, int to) = 0;
  virtual void receive_bytes(void* data, std::size_t bytes, int from) = 0;
  // Copies rank `root`'s bytes to every rank.
  virtual void broadcast_bytes(void* data, std::size_t bytes, int root) = 0;
  virtual void barrier() {}

  template <class T>
  void send(const T* data, index_t n, int to) { send_bytes(data, static_cast<std::size_t>(n) * sizeof(T), to); }
  template <class T>
  void receive(T* data, index_t n, int from) { receive_bytes(data, static_cast<std::size_t>(n) * sizeof(T), from); }
  template <class T>
  void broadcast(T* data, index_t n, int root) { broadcast_bytes(data, static_cast<std::size_t>(n) * sizeof(T), root); }
};

// One process: every scene is its own, so nothing is ever sent.
class SoloCommunicator final : public Communicator {
public:
  int rank() const override { return 0; }
  int size() const override { return 1; }
  void send_bytes(const void*, std::size_t, int to) override { fail("SoloCommunicator: send to rank ", to); }
  void receive_bytes(void*, std::size_t, int from) override { fail("SoloCommunicator: receive from rank ", from); }
  void broadcast_bytes(void*, std::size_t, int root) override {
    require(root == 0, "SoloCommunicator: broadcast from rank ", root);
  }
};

// Which rank computes each scene of a global batch: owner[s] for scene s, in global order.
struct ScenePlan {
  std::vector<int> owner;

  index_t global() const { return static_cast<index_t>(owner.size()); }
  // Rank `rank`'s scenes, in global order.
  std::vector<index_t> scenes_of(int rank) const {
    std::vector<index_t> out;
    for (index_t s = 0; s < global(); ++s)
      if (owner[static_cast<std::size_t>(s)] == rank) out.push_back(s);
    return out;
  }
};

namespace detail {
// Scenes per rank: global / size each, the first global % size ranks one more.
inline std::vector<index_t> plan_counts(index_t global, int size) {
  require(size >= 1, "data parallel: ", size, " ranks");
  require(global >= size, "data parallel: global batch of ", global, " scenes cannot feed ", size,
          " ranks (each rank needs at least one scene)");
  std::vector<index_t> counts(static_cast<std::size_t>(size), global / size);
  for (index_t r = 0; r < global % size; ++r) ++counts[static_cast<std::size_t>(r)];
  return counts;
}
}  // namespace detail

// Contiguous shares in rank order (the first global % size ranks one more scene).
inline ScenePlan contiguous_plan(index_t global, int size) {
  const std::vector<index_t> counts = detail::plan_counts(global, size);
  ScenePlan p;
  for (int r = 0; r < size; ++r) p.owner.insert(p.owner.end(), static_cast<std::size_t>(counts[std::size_t(r)]), r);
  return p;
}

// The same number of scenes per rank as contiguous_plan, chosen by cost: most expensive first, each to the least
// loaded rank with room (ties: the lower rank). Ranks that wait for the slowest one at every step's sum lose their
// time; with equal counts, a cost common to every scene cancels, so `cost` need only rank the scenes' extra work.
inline ScenePlan balanced_plan(std::span<const index_t> cost, int size) {
  const index_t global = static_cast<index_t>(cost.size());
  std::vector<index_t> room = detail::plan_counts(global, size), load(static_cast<std::size_t>(size), 0);
  std::vector<index_t> order(static_cast<std::size_t>(global));
  std::iota(order.begin(), order.end(), index_t(0));
  std::stable_sort(order.begin(), order.end(), [&](index_t a, index_t b) {
    return cost[static_cast<std::size_t>(a)] > cost[static_cast<std::size_t>(b)];
  });
  ScenePlan p;
  p.owner.assign(static_cast<std::size_t>(global), -1);
  for (const index_t s : order) {
    int best = -1;
    for (int r = 0; r < size; ++r)
      if (room[std::size_t(r)] > 0 && (best < 0 || load[std::size_t(r)] < load[std::size_t(best)])) best = r;
    p.owner[static_cast<std::size_t>(s)] = best;
    --room[std::size_t(best)];
    load[std::size_t(best)] += cost[static_cast<std::size_t>(s)];
  }
  return p;
}

// total[n] = sum over the global batch, in global order, of the per-scene vectors; `local` holds this rank's scenes
// (plan.scenes_of(rank), in order). The first scene of the batch is copied, every later one added, on every rank count
// and plan alike.
template <class T>
void ordered_sum(Communicator& comm, T* total, index_t n, const ScenePlan& plan, std::span<const T* const> local) {
  const int me = comm.rank();
  const index_t global = plan.global();
  require(global >= 1 && !local.empty(), "ordered_sum: rank ", me, " has no scenes");
  const std::size_t mine = plan.scenes_of(me).size();
  require(mine == local.size(), "ordered_sum: rank ", me, " holds ", local.size(), " scenes, its plan ", mine);
  auto owner = [&](index_t s) { return plan.owner[static_cast<std::size_t>(s)]; };
  for (index_t s = 0; s < global; ++s)
    require(owner(s) >= 0 && owner(s) < comm.size(), "ordered_sum: scene ", s, " belongs to rank ", owner(s), " of ",
            comm.size());
  std::size_t next = 0;
  for (index_t s = 0; s < global; ++s) {
    if (owner(s) != me) continue;
    const T* g = local[next++];
    if (s == 0) std::memcpy(total, g, static_cast<std::size_t>(n) * sizeof(T));
    else {
      if (owner(s - 1) != me) comm.receive(total, n, owner(s - 1));
      for (index_t i = 0; i < n; ++i) total[i] += g[i];
    }
    if (s + 1 < global && owner(s + 1) != me) comm.send(static_cast<const T*>(total), n, owner(s + 1));
  }
  comm.broadcast(total, n, owner(global - 1));
}

// A scalar (a loss) summed the same way.
template <class T>
T ordered_sum(Communicator& comm, const ScenePlan& plan, std::span<const T> local_values) {
  std::vector<const T*> ptrs;
  for (const T& v : local_values) ptrs.push_back(&v);
  T total{};
  ordered_sum<T>(comm, &total, 1, plan, std::span<const T* const>(ptrs.data(), ptrs.size()));
  return total;
}

#if defined(FLEXSPLAT_WITH_MPI)
// MPI_COMM_WORLD; initialises MPI if nobody has, and finalises it only then.
class MpiCommunicator final : public Communicator {
public:
  MpiCommunicator() {
    int ready = 0;
    MPI_Initialized(&ready);
    if (!ready) {
      MPI_Init(nullptr, nullptr);
      owns_ = true;
    }
    MPI_Comm_rank(MPI_COMM_WORLD, &rank_);
    MPI_Comm_size(MPI_COMM_WORLD, &size_);
  }
  ~MpiCommunicator() override {
    int done = 0;
    MPI_Finalized(&done);
    if (owns_ && !done) MPI_Finalize();
  }
  MpiCommunicator(const MpiCommunicator&) = delete;
  MpiCommunicator& operator=(const MpiCommunicator&) = delete;

  int rank() const override { return rank_; }
  int size() const override { return size_; }
  void send_bytes(const void* d, std::size_t bytes, int to) override {
    chunks(bytes, [&](std::size_t at, int count) {
      check(MPI_Send(static_cast<const char*>(d) + at, count, MPI_BYTE, to, tag, MPI_COMM_WORLD), "send");
    });
  }
  void receive_bytes(void* d, std::size_t bytes, int from) override {
    chunks(bytes, [&](std::size_t at, int count) {
      check(MPI_Recv(static_cast<char*>(d) + at, count, MPI_BYTE, from, tag, MPI_COMM_WORLD, MPI_STATUS_IGNORE),
            "receive");
    });
  }
  void broadcast_bytes(void* d, std::size_t bytes, int root) override {
    if (size_ == 1) return;
    chunks(bytes, [&](std::size_t at, int count) {
      check(MPI_Bcast(static_cast<char*>(d) + at, count, MPI_BYTE, root, MPI_COMM_WORLD), "broadcast");
    });
  }
  void barrier() override { MPI_Barrier(MPI_COMM_WORLD); }

private:
  static constexpr int tag = 7301;
  // MPI counts are int: long buffers go in chunks.
  template <class F>
  static void chunks(std::size_t bytes, F&& f) {
    const std::size_t step = INT_MAX / 2;
    for (std::size_t at = 0; at < bytes; at += step) f(at, static_cast<int>(std::min(step, bytes - at)));
  }
  void check(int code, const char* what) const {
    require(code == MPI_SUCCESS, "MPI ", what, " failed on rank ", rank_, " of ", size_, " (code ", code, ")");
  }
  int rank_ = 0, size_ = 1;
  bool owns_ = false;
};
#endif

}  // namespace train
}  // namespace v0
}  // namespace flexsplat
