// SPDX-License-Identifier: MIT
// Copyright (c) 2026 the burrforce authors
//
// Game-thread glue: start the core's MeshSync once the session is known, and turn changed
// chunks into procedural mesh sections. The fetching and parsing happen on MeshSync's worker.

#include "BurrforceBoneMeshComponent.h"

#include "Async/Async.h"
#include "BurrforceComponent.h"
#include "BurrforceCore.h"
#include "GameFramework/Actor.h"
#include "Materials/MaterialInterface.h"

#include <map>
#include <memory>

struct FBurrforceMeshRuntime
{
	std::shared_ptr<burrforce::MeshSync> Sync;
	/// Chunks changed and not yet uploaded, shared with MeshSync's copy (never copied); null
	/// means "remove its section".
	std::map<burrforce::mesh::ChunkKey, burrforce::mesh::ChunkPtr> Pending;
};

UBurrforceBoneMeshComponent::UBurrforceBoneMeshComponent(
	const FObjectInitializer& ObjectInitializer)
	: Super(ObjectInitializer)
{
	PrimaryComponentTick.bCanEverTick = true;
	bUseAsyncCooking = true;
}

void UBurrforceBoneMeshComponent::BeginPlay()
{
	Super::BeginPlay();
	// Chunk vertices are world positions in the session frame: keep this at the origin.
	SetUsingAbsoluteLocation(true);
	SetUsingAbsoluteRotation(true);
	SetUsingAbsoluteScale(true);
	SetWorldTransform(FTransform::Identity);
	if (!Source && GetOwner())
	{
		Source = GetOwner()->FindComponentByClass<UBurrforceComponent>();
	}
}

void UBurrforceBoneMeshComponent::EndPlay(const EEndPlayReason::Type EndPlayReason)
{
	if (Runtime.IsValid() && Runtime->Sync)
	{
		// The worker may be inside an HTTP request (up to its timeout): ask it to stop and
		// let another thread wait for it; the last reference joins it there.
		std::shared_ptr<burrforce::MeshSync> Sync = std::move(Runtime->Sync);
		Sync->request_stop();
		// Moved, not copied: had the game thread kept a reference, it could be the last one.
		Async(EAsyncExecution::Thread, [Sync = std::move(Sync)]() mutable { Sync.reset(); });
	}
	Runtime.Reset();
	Super::EndPlay(EndPlayReason);
}

void UBurrforceBoneMeshComponent::TryStart()
{
	FString Url, Token;
	int32 Session = 0;
	if (!Source || !Source->GetRestAccess(Url, Token, Session))
	{
		return;  // not connected yet (or no REST access: existing-session mode)
	}
	try
	{
		burrforce::MeshSyncConfig Cfg;
		Cfg.session = static_cast<uint32>(Session);
		Cfg.winding = burrforce::mesh_winding(burrforce::frames::unreal());
		Cfg.frame = "session";
		Cfg.chunk_bricks = ChunkBricks;
		TFunction<uint64()> Version = Source->MakeBoneVersionSource();
		Runtime = MakeShared<FBurrforceMeshRuntime>();
		Runtime->Sync = std::make_shared<burrforce::MeshSync>(
			burrforce::Rest(BurrforceUE::ToStd(Url), BurrforceUE::ToStd(Token)), Cfg,
			[Version]() { return static_cast<uint64_t>(Version()); });
		Runtime->Sync->start();
	}
	catch (const std::exception& E)
	{
		UE_LOG(LogBurrforce, Error, TEXT("burrforce mesh: %s"), *BurrforceUE::ToUE(E.what()));
		Runtime.Reset();
	}
}

void UBurrforceBoneMeshComponent::TickComponent(float DeltaTime, ELevelTick TickType,
	FActorComponentTickFunction* ThisTickFunction)
{
	Super::TickComponent(DeltaTime, TickType, ThisTickFunction);
	if (!Runtime.IsValid())
	{
		TryStart();
		return;
	}
	// Under MeshSync's lock only pointers change hands (a first full copy is hundreds of
	// chunks); the sections are built from the shared, immutable chunks outside it.
	for (burrforce::mesh::ChunkChange& Change : Runtime->Sync->take_changes())
	{
		Runtime->Pending[Change.key] = std::move(Change.chunk);
	}
	Runtime->Sync->read([this](const burrforce::mesh::ChunkedMesh& Mesh)
	{
		ChunkCount = static_cast<int32>(Mesh.size());
		MeshBoneVersion = static_cast<int64>(Mesh.have());
	});
	SyncErrors = static_cast<int64>(Runtime->Sync->errors());
	UploadPending();
}

void UBurrforceBoneMeshComponent::UploadPending()
{
	int32 Budget = MaxSectionsPerTick;
	auto It = Runtime->Pending.begin();
	while (It != Runtime->Pending.end() && Budget-- > 0)
	{
		const FIntVector Key(It->first.a, It->first.b, It->first.c);
		int32* Existing = SectionOfChunk.Find(Key);
		if (!It->second)
		{
			if (Existing)
			{
				ClearMeshSection(*Existing);
				FreeSections.Add(*Existing);
				SectionOfChunk.Remove(Key);
			}
		}
		else
		{
			const burrforce::mesh::Chunk& C = *It->second;
			int32 Section = Existing ? *Existing
				: (FreeSections.Num() ? FreeSections.Pop() : SectionOfChunk.Num() + FreeSections.Num());
			if (!Existing)
			{
				SectionOfChunk.Add(Key, Section);
			}
			const int32 V = static_cast<int32>(C.vertex_count());
			TArray<FVector> Vertices;
			TArray<FVector> Normals;
			TArray<FColor> Colors;
			Vertices.SetNumUninitialized(V);
			Normals.SetNumUninitialized(V);
			Colors.SetNumUninitialized(V);
			for (int32 I = 0; I < V; ++I)
			{
				Vertices[I] = FVector(C.positions[3 * I], C.positions[3 * I + 1],
					C.positions[3 * I + 2]);
				Normals[I] = FVector(C.normals[3 * I], C.normals[3 * I + 1], C.normals[3 * I + 2]);
				const uint8 Label = C.materials[I];
				Colors[I] = LabelColors.IsValidIndex(Label) ? LabelColors[Label] : FColor::White;
			}
			TArray<int32> Triangles;
			Triangles.SetNumUninitialized(static_cast<int32>(C.triangles.size()));
			for (int32 I = 0; I < Triangles.Num(); ++I)
			{
				Triangles[I] = static_cast<int32>(C.triangles[I]);
			}
			CreateMeshSection(Section, Vertices, Triangles, Normals, TArray<FVector2D>(),
				Colors, TArray<FProcMeshTangent>(), /*bCreateCollision=*/false);
			if (BoneMaterial)
			{
				SetMaterial(Section, BoneMaterial);
			}
		}
		It = Runtime->Pending.erase(It);
	}
}
