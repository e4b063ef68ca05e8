#pragma once
// Data parallelism with results independent of the process count. The global batch's per-scene gradients are summed
// sequentially in global scene order: rank r receives the running sum of ranks 0..r-1, adds its own scenes in order and
// passes it on; the last rank broadcasts the total. One process runs the same additions in the same order, so N ranks
// give bit-identical parameters to one process with the same global batch. The chain costs (ranks - 1) messages of the
// gradient size per step, which suits the few-node clusters this targets; MPI's tree reductions would be faster but
// their order depends on the rank count.
//
// MPI is optional: MpiCommunicator exists only where the including target defines FLEXSPLAT_WITH_MPI and links MPI
// (the build's FLEXSPLAT_MPI option does that for the command-line program and tests).
#include <algorithm>
#include <climits>
#include <cstring>
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
  // Blocks until `data` holds the running sum from the previous rank (rank 0: untouched).
  virtual void receive_partial(float* data, index_t n) = 0;
  virtual void receive_partial(double* data, index_t n) = 0;
  // Passes the running sum to the next rank (the last rank: nothing).
  virtual void send_partial(const float* data, index_t n) = 0;
  virtual void send_partial(const double* data, index_t n) = 0;
  // Copies the last rank's `data` to every rank.
  virtual void broadcast_from_last(float* data, index_t n) = 0;
  virtual void broadcast_from_last(double* data, index_t n) = 0;
  // Copies rank 0's `data` to every rank.
  virtual void broadcast_from_first(float* data, index_t n) = 0;
  virtual void broadcast_from_first(double* data, index_t n) = 0;
  virtual void barrier() {}
};

// One process: every hook is a no-op.
class SoloCommunicator final : public Communicator {
public:
  int rank() const override { return 0; }
  int size() const override { return 1; }
  void receive_partial(float*, index_t) override {}
  void receive_partial(double*, index_t) override {}
  void send_partial(const float*, index_t) override {}
  void send_partial(const double*, index_t) override {}
  void broadcast_from_last(float*, index_t) override {}
  void broadcast_from_last(double*, index_t) override {}
  void broadcast_from_first(float*, index_t) override {}
  void broadcast_from_first(double*, index_t) override {}
};

// Which scenes of a global batch of `global` scenes a rank computes: contiguous, the first `global % size` ranks one
// more, so concatenating the ranks' shares in rank order gives the global order.
struct Share {
  index_t first = 0, count = 0;
};

inline Share share_of(index_t global, int rank, int size) {
  require(size >= 1 && rank >= 0 && rank < size, "share_of: rank ", rank, " of ", size);
  require(global >= size, "data parallel: global batch of ", global, " scenes cannot feed ", size,
          " ranks (each rank needs at least one scene)");
  const index_t base = global / size, extra = global % size;
  Share s;
  s.first = rank * base + std::min<index_t>(rank, extra);
  s.count = base + (rank < extra ? 1 : 0);
  return s;
}

// total[n] = sum over the global batch, in global order, of the per-scene vectors; `local` holds this rank's scenes
// (in order). The first scene of the batch is copied, every later one added, on every rank count alike.
template <class T>
void ordered_sum(Communicator& comm, T* total, index_t n, std::span<const T* const> local) {
  require(!local.empty(), "ordered_sum: rank ", comm.rank(), " has no scenes");
  std::size_t first = 0;
  if (comm.rank() == 0) {
    std::memcpy(total, local[0], static_cast<std::size_t>(n) * sizeof(T));
    first = 1;
  } else {
    comm.receive_partial(total, n);
  }
  for (std::size_t s = first; s < local.size(); ++s) {
    const T* g = local[s];
    for (index_t i = 0; i < n; ++i) total[i] += g[i];
  }
  comm.send_partial(total, n);
  comm.broadcast_from_last(total, n);
}

// A scalar (a loss) summed the same way.
template <class T>
T ordered_sum(Communicator& comm, std::span<const T> local_values) {
  std::vector<const T*> ptrs;
  for (const T& v : local_values) ptrs.push_back(&v);
  T total{};
  ordered_sum<T>(comm, &total, 1, std::span<const T* const>(ptrs.data(), ptrs.size()));
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
  void receive_partial(float* d, index_t n) override { recv(d, n, MPI_FLOAT); }
  void receive_partial(double* d, index_t n) override { recv(d, n, MPI_DOUBLE); }
  void send_partial(const float* d, index_t n) override { send(d, n, MPI_FLOAT); }
  void send_partial(const double* d, index_t n) override { send(d, n, MPI_DOUBLE); }
  void broadcast_from_last(float* d, index_t n) override { bcast(d, n, MPI_FLOAT, size_ - 1); }
  void broadcast_from_last(double* d, index_t n) override { bcast(d, n, MPI_DOUBLE, size_ - 1); }
  void broadcast_from_first(float* d, index_t n) override { bcast(d, n, MPI_FLOAT, 0); }
  void broadcast_from_first(double* d, index_t n) override { bcast(d, n, MPI_DOUBLE, 0); }
  void barrier() override { MPI_Barrier(MPI_COMM_WORLD); }

private:
  static constexpr int tag = 7301;
  // MPI counts are int: long vectors go in chunks.
  template <class F>
  static void chunks(index_t n, std::size_t elem, F&& f) {
    const index_t step = INT_MAX / 2;
    for (index_t at = 0; at < n; at += step) f(at * static_cast<index_t>(elem), static_cast<int>(std::min(step, n - at)));
  }
  void recv(void* d, index_t n, MPI_Datatype t) {
    if (rank_ == 0) return;
    int elem = 0;
    MPI_Type_size(t, &elem);
    chunks(n, static_cast<std::size_t>(elem), [&](index_t byte, int count) {
      check(MPI_Recv(static_cast<char*>(d) + byte, count, t, rank_ - 1, tag, MPI_COMM_WORLD, MPI_STATUS_IGNORE), "receive");
    });
  }
  void send(const void* d, index_t n, MPI_Datatype t) {
    if (rank_ == size_ - 1) return;
    int elem = 0;
    MPI_Type_size(t, &elem);
    chunks(n, static_cast<std::size_t>(elem), [&](index_t byte, int count) {
      check(MPI_Send(static_cast<const char*>(d) + byte, count, t, rank_ + 1, tag, MPI_COMM_WORLD), "send");
    });
  }
  void bcast(void* d, index_t n, MPI_Datatype t, int root) {
    if (size_ == 1) return;
    int elem = 0;
    MPI_Type_size(t, &elem);
    chunks(n, static_cast<std::size_t>(elem), [&](index_t byte, int count) {
      check(MPI_Bcast(static_cast<char*>(d) + byte, count, t, root, MPI_COMM_WORLD), "broadcast");
    });
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
