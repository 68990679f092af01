// peer_many: tinybvh's one-thread loop over many meshes in one process (bench_batch.py).
//
//   peer_many MESHES.bin [--opt-iters K]
//
// MESHES.bin (little-endian): uint32 M, then per mesh uint32 N and N*9 float32 triangles
// (v0 xyz, v1 xyz, v2 xyz), as bench_batch.py writes it. For each mesh, in order:
// BVH::Build (binned SAH, one thread) timed, then BVH::Optimize(K, extreme=true) on that
// tree timed (K = 200 by default, the peer harness's setting). Prints one JSON line with
// the total milliseconds of each loop and the mean SAH (Ct = Ci = 1, normalised by the
// root's area, computed in double as ../shared/peer/tinybvh_bench.cpp does).
// Built from the unmodified ../shared/peer/tiny_bvh.h (MIT, Jacco Bikker).

#define TINYBVH_IMPLEMENTATION
#define NO_THREADED_BUILDS
#include "tiny_bvh.h"

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <string>
#include <unistd.h>
#include <vector>

using namespace tinybvh;
using Clock = std::chrono::steady_clock;

static double Ms( Clock::time_point t0 ) { return std::chrono::duration<double, std::milli>( Clock::now() - t0 ).count(); }

static double Area( const bvhvec3& lo, const bvhvec3& hi )
{
	const double dx = std::max( 0.0, (double)hi.x - lo.x ), dy = std::max( 0.0, (double)hi.y - lo.y ),
		dz = std::max( 0.0, (double)hi.z - lo.z );
	return 2.0 * (dx * dy + dy * dz + dz * dx);
}

// SAH with Ct = Ci = 1 over the nodes reachable from the root, normalised by its area
static double Sah( const BVH& bvh )
{
	double total = 0;
	std::vector<uint32_t> stack{ 0 };
	while (!stack.empty())
	{
		const BVH::BVHNode& n = bvh.bvhNode[stack.back()];
		stack.pop_back();
		const double a = Area( n.aabbMin, n.aabbMax );
		if (n.isLeaf()) total += a * n.triCount;
		else total += a, stack.push_back( n.leftFirst ), stack.push_back( n.leftFirst + 1 );
	}
	const double root = Area( bvh.bvhNode[0].aabbMin, bvh.bvhNode[0].aabbMax );
	return root > 0 ? total / root : 0.0;
}

int main( int argc, char** argv )
{
	fflush( stdout );
	const int jsonFd = dup( 1 );
	FILE* out = jsonFd >= 0 ? fdopen( jsonFd, "w" ) : stdout;
	if (out != stdout) dup2( 2, 1 ); // tinybvh's own prints go to stderr
	if (argc < 2) { fprintf( stderr, "usage: peer_many MESHES.bin [--opt-iters K]\n" ); return 2; }
	uint32_t iters = 200;
	for (int i = 2; i + 1 < argc; i++) if (std::string( argv[i] ) == "--opt-iters") iters = (uint32_t)atoi( argv[i + 1] );
	FILE* in = fopen( argv[1], "rb" );
	if (!in) { fprintf( stderr, "cannot open %s\n", argv[1] ); return 1; }
	uint32_t meshes = 0;
	if (fread( &meshes, 4, 1, in ) != 1) return 1;
	double buildMs = 0, optMs = 0, sahBuilt = 0, sahOpt = 0;
	size_t tris = 0;
	for (uint32_t m = 0; m < meshes; m++)
	{
		uint32_t n = 0;
		if (fread( &n, 4, 1, in ) != 1 || n == 0) { fprintf( stderr, "bad mesh %u\n", m ); return 1; }
		std::vector<float> raw( (size_t)n * 9 );
		if (fread( raw.data(), 4, raw.size(), in ) != raw.size()) { fprintf( stderr, "short file\n" ); return 1; }
		bvhvec4* verts = (bvhvec4*)malloc64( (((size_t)n * 3 * sizeof( bvhvec4 )) + 63) & ~(size_t)63 );
		for (size_t v = 0; v < (size_t)n * 3; v++) verts[v] = bvhvec4( raw[v * 3], raw[v * 3 + 1], raw[v * 3 + 2], 0 );
		BVH* bvh = new BVH();
		Clock::time_point t0 = Clock::now();
		bvh->Build( verts, n );
		buildMs += Ms( t0 );
		sahBuilt += Sah( *bvh );
		t0 = Clock::now();
		bvh->Optimize( iters, true );
		optMs += Ms( t0 );
		sahOpt += Sah( *bvh );
		delete bvh;
		free64( verts );
		tris += n;
	}
	fprintf( out, "{\"meshes\":%u,\"triangles\":%zu,\"build_ms\":%.3f,\"optimize_ms\":%.3f,"
		"\"sah_built_mean\":%.6f,\"sah_optimized_mean\":%.6f,\"opt_iters\":%u}\n",
		meshes, tris, buildMs, optMs, sahBuilt / meshes, sahOpt / meshes, iters );
	fflush( out );
	return 0;
}
